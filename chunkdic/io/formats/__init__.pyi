from .ingest import ingest, slab_chunks
from .openers import natural_key, open_source, open_tiff_file
from .readers import H5Reader, NpyReader, RawReader, Reader, TiffSlicesReader, TiffVolumeReader
from .anyscan import is_foreign, open_any
