from .launch import view
from .layers import fields_layers, find_fields, layers_of, result_layers, series_layers
from .mesh_layers import MAX_VECTORS, weak_layer
from .reader import napari_get_reader
