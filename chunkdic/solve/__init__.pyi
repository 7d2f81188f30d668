from .cg import PoorTextureWarning, StencilSolver, warmup
from .multigrid import VCycle
from .regchoice import choose_length
from .regularizer import Regularizer
from .stencil import stencil_matvec
