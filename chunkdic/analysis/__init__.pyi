from .crosscheck import cutcheck
from .loadseries import SeriesResult, open_series, series
from .metrology import fit_power_law, uncertainty
from .q4 import correlate2d
from .scoring import score_displacement
from .texture import TextureReport, texture
from .zoisweep import sweep, zoi_table
