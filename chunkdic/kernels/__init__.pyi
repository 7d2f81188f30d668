from .jit import compiled_on_disk, warmup
