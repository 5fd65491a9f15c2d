"""`toolkit eval`: SuperPoint's HPatches evaluation protocol for any model through one adapter path.

Modules: `datasets` (HPatches and registered-pair layouts, H files, resizing), `metrics` (the per-pair
metrics), `detectors` (``--model`` spec -> detector), `runner` (pairs loop, aggregation), `report` (outputs).
"""
