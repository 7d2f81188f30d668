from .driver import correlate
from .front import RunSpec, prepare_run
from .meshes import plan_meshes
from .runplan import Plan, plan
from .texture_check import ElementSizeWarning
