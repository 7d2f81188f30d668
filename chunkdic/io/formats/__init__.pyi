from .anyscan import open_any
from .base import Format, Layout, Reader, Source, natural_key
from .detect import FORMATS, is_foreign, open_source
from .hdf5 import H5Reader
from .ingest import ingest, slab_chunks
from .npy import NpyReader
from .raw import RawReader
from .tiff import TiffSlicesReader, TiffVolumeReader, open_tiff_file
