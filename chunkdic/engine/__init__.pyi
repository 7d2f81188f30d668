from .driver import correlate
from .meshes import plan_meshes
