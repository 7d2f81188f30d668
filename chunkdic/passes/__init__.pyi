from .dense import DensePasses
from .level import LevelPasses
