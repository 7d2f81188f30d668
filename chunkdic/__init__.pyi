# The public API: every name here is importable as ``chunkdic.NAME`` and loaded on first use.
from .analysis.crosscheck import cutcheck
from .analysis.loadseries import SeriesResult, open_series, series
from .analysis.metrology import fit_power_law, uncertainty
from .analysis.q4 import correlate2d
from .analysis.resolution import resolution
from .analysis.scoring import score_displacement
from .analysis.texture import TextureReport, texture
from .analysis.zoisweep import sweep, zoi_table
from .engine.budget import Plan, plan
from .engine.driver import correlate
from .engine.settings import Settings
from .engine.texturestats import ElementSizeWarning
from .errors import InputError
from .io.display import write_display
from .io.formats.ingest import ingest
from .io.handles import ArrayRef
from .io.masking import make_mask
from .io.pyramid import build_pyramid
from .io.scan import Scan, open_scan
from .io.scanwrite import write_scan
from .mesh import Mesh
from .results.result import Result, open_result
from .results.strain import element_strain, mean_strain
from .solve.cg import PoorTextureWarning
from .views.corrected_image import write_corrected
from .views.export import write_nodes_csv, write_vtk
from .views.fields import open_fields, write_fields
from .views.report import report

__version__: str

def show_versions() -> str: ...
