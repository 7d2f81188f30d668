from .display import write_display
from .formats.ingest import ingest
from .handles import ArrayRef
from .kinds import kind_of
from .masking import make_mask
from .outputs import Outputs, check_output
from .locks import OutputLock
from .scratch import make_scratch
from .pyramid import build_pyramid
from .scan import Scan, open_scan
from .scanwrite import write_scan
from .units import parse_length
