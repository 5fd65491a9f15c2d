"""One graph per onnxruntime channel block: the deployed graph padded for each of a profile's blocks, checked
against the graph as traced (`block_graphs`).

`export.channel_padding` pads a chain around a max-pool to a multiple of one block. Which block onnxruntime
uses depends on the CPU it runs on (16 with AVX-512F, 8 with AVX2: `vo_runtime.cpu_blocks`), and a graph padded for
16 is slower where the block is 8 (the slim network at 480x752: 0.8-1.1 ms a frame on an AVX2 core). So the artefact
keeps the traced graph and adds a padded copy per block that has something to pad; the runtime picks one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import onnx

from export.channel_padding import PaddedChain, pad_pooled_channels
from export.errors import ExportError
from export.parity import cpu_session

# Largest output difference between a padded graph and the traced one on the parity images. Zero channels add
# exact zeros, and the outputs were the same to the bit on the AVX2 and AVX-512 cores measured; the bound leaves
# room for a kernel that sums in another order, not for a wrong graph.
MAX_BLOCK_DIFF = 1e-4


@dataclass
class BlockGraph:
    """The deployed graph padded for onnxruntime's ``block``-channel layout."""

    block: int
    model: onnx.ModelProto
    chains: list[PaddedChain]
    max_abs_diff: float  # against the traced graph, over every output and parity image

    @property
    def file_name(self) -> str:
        return f"model.block{self.block}.onnx"


def block_graphs(traced: onnx.ModelProto, blocks: tuple[int, ...], images: list[np.ndarray],
                 finish: Callable[[onnx.ModelProto], onnx.ModelProto]) -> list[BlockGraph]:
    """For each of ``blocks``, ``traced`` (the float32 graph) padded by `pad_pooled_channels` and passed through
    ``finish`` (the FP16 conversion, or nothing); kept where a chain was padded. Each kept graph runs beside
    ``finish(traced)``, the graph deployed as model.onnx, on ``images`` [1, 1, H, W]: an output differing by more
    than `MAX_BLOCK_DIFF` is an `ExportError`."""
    padded = []
    for block in blocks:
        model, chains = pad_pooled_channels(traced, block)
        if chains:
            padded.append((block, finish(model), chains))
    if not padded:
        return []
    base = cpu_session(finish(traced))
    expected = [base.run(None, {"image": image}) for image in images]
    graphs = []
    for block, model, chains in padded:
        session = cpu_session(model)
        worst = 0.0
        for image, reference in zip(images, expected):
            for got, want in zip(session.run(None, {"image": image}), reference):
                worst = max(worst, float(np.abs(got.astype(np.float64) - want).max()) if want.size else 0.0)
        if not worst <= MAX_BLOCK_DIFF:
            raise ExportError(f"the graph padded for {block}-channel blocks differs from the traced one by {worst:.3g} "
                              f"(at most {MAX_BLOCK_DIFF} allowed): export with a profile without channel_blocks")
        graphs.append(BlockGraph(block, model, chains, worst))
    return graphs
