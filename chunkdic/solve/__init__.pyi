from .cg import PoorTextureWarning, StencilSolver, warmup
from .stencil import stencil_matvec
from .multigrid import VCycle
from .regchoice import choose_length
from .regularization import Regularizer
