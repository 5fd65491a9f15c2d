"""The README written into each artefact: what it is and the exact on-device step that remains."""
from __future__ import annotations

from profiles import TargetProfile


def _tx2_steps(manifest: dict) -> str:
    fp16 = " --fp16" if manifest["precision"] == "fp16" else ""
    engine = f"model_{manifest['precision']}.engine"
    return f"""## Build the TensorRT engine on the TX2

Engines are specific to the device and the TensorRT version, so build it on the Jetson itself
(JetPack 4.6 = TensorRT 8.0.1, or 4.6.1 = TensorRT 8.2.1):

```
sudo nvpmodel -m 0 && sudo jetson_clocks   # MAXN: GPU at 1.30 GHz
/usr/src/tensorrt/bin/trtexec --onnx=model.onnx{fp16} --workspace=1024 --saveEngine={engine}
```

The graph is opset {manifest['onnx']['opset']} with fixed shapes and only ops TensorRT 8.0 parses (the deformable conv is
decomposed into Gather + arithmetic). Inputs and outputs stay FP32; `--fp16` lets TensorRT run layers in FP16.
Every gather index is int32 arithmetic on values exact in FP16, so whichever layers TensorRT puts in FP16,
keypoints stay in place (checked on a CPU with every layer converted to FP16: >= 98.7 % of keypoints within
0.5 px of FP32; not yet run on a TX2). Check the engine against this directory's parity run (the inputs
and outputs in reference.npz), with the runtime installed on the Jetson:

```
python -m vo_runtime verify . --engine {engine}      # the engine itself, run by trtexec
python -m vo_runtime verify . --providers tensorrt     # onnxruntime's TensorRT provider (FP16), as the VO runs it
```

Do not build INT8: the TX2's Pascal GPU has no fast INT8 path.
"""


def _cpu_steps(manifest: dict) -> str:
    return f"""## Run on an x86 CPU

onnxruntime >= 1.25 (the ONNX `DeformConv` op, opset {manifest['onnx']['opset']}). From Python, without torch:

```
from vo_runtime import FeatureExtractor
extract = FeatureExtractor("path/to/this/directory", threads=2)
features = extract(gray_or_bgr_image)   # keypoints [N,2], scores [N], descriptors [N,D]
```

Check that this machine's onnxruntime reproduces the parity run (the inputs and outputs in reference.npz):
`python -m vo_runtime verify path/to/this/directory`.
{_block_lines(manifest)}"""


def _block_lines(manifest: dict) -> str:
    graphs = manifest["onnx"].get("block_graphs", [])
    if not graphs:
        return ""
    lines = [f"- `{graph['file']}`: padded with zero channels for {graph['block']}-channel blocks "
             f"(outputs within {graph['max_abs_diff']:.1e} of model.onnx)" for graph in graphs]
    return ("\nThe same network padded for onnxruntime's channel blocks (16 with AVX-512, 8 with AVX2); "
            "`FeatureExtractor` loads the one for its CPU:\n" + "\n".join(lines) + "\n")


def artefact_readme(manifest: dict, profile: TargetProfile) -> str:
    height, width = manifest["input"]["shape"][2:]
    parity = manifest["parity"]
    steps = _tx2_steps(manifest) if profile.name == "tx2" else _cpu_steps(manifest)
    outputs = "\n".join(f"- `{name}` {spec['shape']} {spec['dtype']}: {spec['meaning']}" for name, spec in manifest["outputs"].items())
    return f"""# EdgeFeat artefact: {manifest['model']['arch']} for {profile.name}

{profile.description}.

- input `image` [1, 1, {height}, {width}] float32: grayscale scaled to [0, 1] (pixel / 255)
- precision: {manifest['precision']} ({manifest['precision_applied']}); deformable conv: {manifest['deform_strategy']}
- model.onnx sha256: `{manifest['onnx']['sha256']}`
- source checkpoint sha256: `{manifest['model']['checkpoint_sha256']}`

Outputs:
{outputs}

Parity against PyTorch on {len(parity['images'])} real images: {parity['keypoints_identical']:.2%} of keypoints identical,
heatmap max abs diff {parity['heatmap_max_abs_diff']:.2e}, descriptor max abs diff {parity['descriptors_coarse_max_abs_diff']:.2e}.

{steps}"""
