"""Compression for deployment: structured channel pruning with distillation, and INT8/FP16 quantisation.

Each step measures its own cost: `prune` reports params, MACs, latency and output drift against the
unpruned network; `quantise` reports per-layer sensitivity and parity against the FP32 artefact.
"""
