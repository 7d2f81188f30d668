from .corrected_image import open_corrected, write_corrected
from .fields_image import write_fields
from .fields_reader import open_fields, open_levels
from .meshfiles import write_nodes_csv, write_vtk
from .ngff_displacements import write_displacements
from .pvd import write_pvd
