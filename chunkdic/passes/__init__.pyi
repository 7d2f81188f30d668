from .level import Level
