from .settings import Settings
from .stopping import History, State, decide
