from .launch import view
from .layers import (
    MAX_VECTORS,
    fields_layers,
    find_fields,
    layers_of,
    result_layers,
    series_layers,
    weak_layer,
)
from .reader import napari_get_reader
