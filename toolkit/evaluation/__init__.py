"""`toolkit eval`: SuperPoint's HPatches evaluation protocol for any model through one adapter path.

Modules: `datasets` (HPatches and registered-pair layouts, H files, resizing), `metrics` (the per-pair
metrics), `detectors` (``--model`` spec -> detector), `runner` (pairs loop, aggregation), `report` (outputs),
`intervals` (bootstrap intervals over sequences), `synth` (sequences generated from frames: `synth_frames`
finds and picks them, `synth_viewpoint` and `synth_darkness` make the targets).
"""
