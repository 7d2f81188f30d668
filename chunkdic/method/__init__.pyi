from .gauss_newton import iterate
from .level_solve import LevelOutcome, run_level, solve_level
from .operator import Operator
from .protocol import Pass, Passes
from .runstate import RunState
from .settings import Settings
from .stopping import History, State, decide
