"""chunkdic's asv benchmarks: small cases (96³–128³) that run in minutes (benchmarks/README.md)."""
