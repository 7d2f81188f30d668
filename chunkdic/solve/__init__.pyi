from .cg import PoorTextureWarning, StencilSolver, warmup
from .haloedfiles import HaloedFiles
from .multigrid import VCycle
from .nodeblocks import DiskHolder, WorkerHolder, node_block_elements, node_chunks
from .partitioned import PartitionedSolver
from .regchoice import choose_length
from .regularizer import Regularizer
from .stencil import stencil_matvec
