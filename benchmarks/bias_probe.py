"""Is the reconstruction's smooth bias (issue 12: the denoised image darker than the
reference, low-frequency error far above the inputs') caused by weights that correlate
with the noise they weight? Two renders of one scene with different seeds, A and B: the
network's weights from A's own features, and from B's (independent noise), applied to
A's estimates. If the darkening vanishes with B's weights, the weights select terms by
their noise (a selection bias that shrinks with N, so consistency is kept, but shows at
low N).

    python benchmarks/bias_probe.py A.exr B.exr REFERENCE.exr [--model CKPT]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.metrics import relmse, relmse_blocks  # noqa: E402
from ppmrecon.model import checkpoint  # noqa: E402
from ppmrecon.model.combine import combine_with_weights  # noqa: E402
from ppmrecon.model.features import buffer_scales, from_buffer  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("reference", type=Path)
    p.add_argument("--model", type=Path, default=checkpoint.DEFAULT_MODEL)
    args = p.parse_args()
    torch.set_num_threads(1)
    model, _ = checkpoint.load_checkpoint(args.model)
    ref = B.read_rgb(args.reference)[0].astype(np.float64)

    def prepared(path: Path):
        buf = B.read_buffers(path)
        h, w = buf.shape
        inp = from_buffer(buf, model.features, (slice(0, h), slice(0, w)), buffer_scales(buf, model.features))
        with torch.no_grad():
            return buf, inp, model.predict(inp.features, "float32")

    def combined(inp, logits) -> np.ndarray:
        with torch.no_grad():
            out = combine_with_weights(inp.y, inp.z, logits, method="loop").image[0].clamp(min=0)
        return out.permute(1, 2, 0).numpy().astype(np.float64)

    def line(name: str, img: np.ndarray) -> None:
        print(f"| {name} | {relmse(img, ref):.4g} | {relmse_blocks(img, ref):.4g} | {img.mean() / ref.mean():.4f} |")

    (buf_a, inp_a, log_a), (buf_b, inp_b, log_b) = prepared(args.a), prepared(args.b)
    print("| image | relMSE | 8x8 relMSE | mean / reference |\n| --- | --- | --- | --- |")
    for k, name in enumerate(B.ESTIMATES):
        line(f"A: input ~{name}", buf_a.estimates[k].astype(np.float64))
    line("A with its own weights", combined(inp_a, log_a))
    line("A with B's weights", combined(inp_a, log_b))
    line("B with its own weights", combined(inp_b, log_b))
    line("B with A's weights", combined(inp_b, log_a))


if __name__ == "__main__":
    main()
