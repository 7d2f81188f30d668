from .corrected_image import open_corrected, write_corrected
from .export import write_nodes_csv, write_vtk
from .fields import open_fields, open_levels, write_fields
from .mechplots import plot_gauge, plot_profile
from .ngff_displacements import write_displacements
from .pvd import write_pvd
