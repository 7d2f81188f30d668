from .ctpair import render_ct
from .fields import Affine, Band, Crack, Star, Translation
from .fourier_shift import fourier_shift_scan
from .shear import Slip, Wave
from .synthetic import load_field, standard_case, synthesize
