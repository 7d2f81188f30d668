from .challenge import challenge_numbers, noise_floors
from .covariance import NodalCovariance
from .cracks import CrackMap, find_cracks
from .crosscheck import cutcheck
from .gauge import gauge
from .loadseries import SeriesResult, open_series, series
from .metrology import fit_power_law, uncertainty
from .q4 import correlate2d
from .regions import Region, region_of
from .repeats import repeat_noise
from .rigid import RigidMotion, fit_rigid, remove_rigid
from .scoring import score_displacement
from .stats import Profile, RegionStats, profile, region_stats, stats
from .texture import TextureReport, texture
from .zoisweep import sweep, zoi_table
