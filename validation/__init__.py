"""Validation studies of chunkdic: one script per study, one record schema, one command.

``python -m validation list`` names the studies, ``python -m validation run STUDY``
measures one again and replaces its record, ``python -m validation check`` checks every
record against the schema (:mod:`validation.record`).
"""
