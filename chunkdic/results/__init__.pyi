from .result import Result, open_result
from .scans import input_scans
from .strain import element_strain, mean_strain
