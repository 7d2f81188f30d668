# The public API: every name here is importable as ``chunkdic.NAME`` and loaded on first use.
from .analysis.cracks import find_cracks
from .analysis.crosscheck import cutcheck
from .analysis.gauge import gauge
from .analysis.loadseries import SeriesResult, open_series, series
from .analysis.metrology import fit_power_law, uncertainty
from .analysis.q4 import correlate2d
from .analysis.repeats import repeat_noise
from .analysis.resolution import resolution
from .analysis.rigid import fit_rigid, remove_rigid
from .analysis.scoring import score_displacement
from .analysis.stats import stats
from .analysis.texture import TextureReport, texture
from .analysis.zoisweep import sweep, zoi_table
from .engine.runplan import Plan, plan
from .engine.driver import correlate
from .engine.texture_check import ElementSizeWarning
from .method.settings import Settings
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
from .export.corrected_image import write_corrected
from .export.meshfiles import write_nodes_csv, write_vtk
from .export.fields_reader import open_fields
from .export.fields_image import write_fields
from .export.ngff_displacements import write_displacements
from .export.pvd import write_pvd
from .plot.report import report

__version__: str

def show_versions() -> str: ...
