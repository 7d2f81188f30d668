from .driver import correlate
from .planning import plan_meshes
from .settings import Settings
from .texturestats import ElementSizeWarning
