from .cg import PoorTextureWarning, StencilSolver, stencil_matvec, warmup
from .multigrid import VCycle
from .regchoice import choose_length
from .regularization import Regularizer
