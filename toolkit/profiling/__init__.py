"""`toolkit profile`: counts (fvcore + ONNX graph), host latency, roofline predictions, calibration, reports.

Modules: `counts` (MACs, parameters, traffic), `latency` (host timing), `roofline` (prediction per layer),
`calibration` (fitting the host's figures), `sources` (what --model accepts), `profile` (one report),
`report` (table, markdown, JSON, PNG).
"""
