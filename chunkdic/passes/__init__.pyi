from .crack_cut import CrackLabels
from .dense import DensePasses
from .level import LevelPasses
