"""Converts LPIPS-VGG weights you have into the one safetensors file `metrics.lpips` loads.

Inputs (neither can be downloaded by this project; both are commonly in a PyTorch cache):
  * torchvision's ImageNet VGG16 state dict, e.g. ~/.cache/torch/hub/checkpoints/
    vgg16-397923af.pth (only `features.*` is kept; the classifier is dropped);
  * the lpips package's linear layers, `lpips/weights/v0.1/vgg.pth` inside the installed package
    (`lin0.model.1.weight` ... `lin4.model.1.weight`).

    python experiments/convert_lpips_weights.py --vgg16 vgg16-397923af.pth \
        --lin .../site-packages/lpips/weights/v0.1/vgg.pth --output lpips_vgg.safetensors

Both are pickles, read with `torch.load(weights_only=True)` (tensors only, no code); this is the
only place the project reads a pickle, on files the user chose. Needs torch. The output is
checked against the names and shapes `metrics.lpips` expects and written atomically.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

import numpy as np

from signerf_jax import files
from signerf_jax import safetensors_io
from signerf_jax.metrics import lpips


def read_state_dict(path: str) -> dict[str, np.ndarray]:
  import torch  # pylint: disable=g-import-not-at-top

  state = torch.load(path, map_location="cpu", weights_only=True)
  return {name: value.detach().to(torch.float32).numpy() for name, value in state.items()}


def convert(vgg16_path: str, lin_path: str, output_path: str) -> None:
  expected = lpips.expected_shapes()
  tensors = {name: value for name, value in read_state_dict(vgg16_path).items()
             if name in expected}
  tensors.update({name: value for name, value in read_state_dict(lin_path).items()
                  if name in expected})
  safetensors_io.check_tensors(expected, tensors, f"{vgg16_path} + {lin_path}")
  from safetensors.numpy import save  # pylint: disable=g-import-not-at-top

  files.write_bytes(output_path, save({name: np.ascontiguousarray(tensors[name])
                                       for name in expected}))


def main(argv: Sequence[str] | None = None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--vgg16", required=True, help="torchvision VGG16 state dict (.pth)")
  parser.add_argument("--lin", required=True, help="lpips weights/v0.1/vgg.pth")
  parser.add_argument("--output", required=True, help="the safetensors file to write")
  args = parser.parse_args(argv)
  convert(args.vgg16, args.lin, args.output)
  print(f"wrote {args.output}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
