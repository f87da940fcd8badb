"""The SuperFlow losses on a spconv MinkUNet, fed by ``superflow.torch.spconv_tensor``:
the 3D network is spconv's (submanifold and strided sparse convolutions that compute
their own maps from the batch's level-0 coordinates), the frozen ViT, the 2D head and
the spatial, temporal and dense-to-sparse contrastive losses are the PyTorch reference of
the Rust trainer (trainer/reference/bench_torch.py).

    printf '[sample]\nkernel_maps = "none"\n' > no-maps.toml   # spconv finds its own maps
    superflow-pipeline --mcap recordings/drives --run exp1 --batch-size 2 --config no-maps.toml &
    python trainer/python/examples/train_spconv.py --run exp1 --steps 20

(It reads a batch with the maps too: it does not use them.)

Trains on a GPU (``pip install spconv-cu120`` or the build of your CUDA, and torch with
CUDA). On a CPU (``pip install "./trainer/python[spconv]"``: spconv's CPU build) it runs
one forward pass and the losses, then stops and says why: spconv's CPU build has no
backward pass (it asks for CUDA). Prints one JSON line per step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import spconv.pytorch as spconv
import torch
import torch.nn.functional as Fn
from torch import nn

import superflow
import superflow.torch as sft

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "reference"))
import bench_torch as ref  # the ViT, 2D head and losses of the Rust trainer


def to(obj, device: torch.device):
    """``obj`` (tensors in lists, tuples and dicts) on ``device``."""
    if torch.is_tensor(obj):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: to(v, device) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to(v, device) for v in obj)
    return obj


def block(cin: int, cout: int, key: str) -> spconv.SparseSequential:
    return spconv.SparseSequential(
        spconv.SubMConv3d(cin, cout, 3, padding=1, bias=False, indice_key=key),
        nn.BatchNorm1d(cout), nn.ReLU())


class SpconvMinkUNet(nn.Module):
    """A MinkUNet in spconv: a submanifold stem, ``len(planes) - 1`` strided (2) sparse
    convolutions down and inverse ones back up with skip connections. The output rows are
    the input rows, in order, so ``point_to_voxel`` and the pairings index them."""

    def __init__(self, cin: int = 4, planes: tuple[int, ...] = (16, 32, 64, 64)):
        super().__init__()
        self.stem = block(cin, planes[0], "subm0")
        self.downs = nn.ModuleList()
        self.ups = nn.ModuleList()
        self.fuse = nn.ModuleList()
        for i in range(len(planes) - 1):
            self.downs.append(spconv.SparseSequential(
                spconv.SparseConv3d(planes[i], planes[i + 1], 2, stride=2, bias=False,
                                    indice_key=f"down{i}"),
                nn.BatchNorm1d(planes[i + 1]), nn.ReLU(),
                block(planes[i + 1], planes[i + 1], f"subm{i + 1}")))
            self.ups.append(spconv.SparseSequential(
                spconv.SparseInverseConv3d(planes[i + 1], planes[i], 2, bias=False,
                                           indice_key=f"down{i}"),
                nn.BatchNorm1d(planes[i]), nn.ReLU()))
            self.fuse.append(block(2 * planes[i], planes[i], f"subm{i}"))
        self.out_channels = planes[0]

    def forward(self, x: spconv.SparseConvTensor) -> torch.Tensor:
        x = self.stem(x)
        skips = []
        for down in self.downs:
            skips.append(x)
            x = down(x)
        for i in reversed(range(len(self.downs))):
            x = self.ups[i](x)
            x = x.replace_feature(torch.cat([x.features, skips[i].features], dim=1))
            x = self.fuse[i](x)
        return x.features


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--pixel-stride", type=int, default=4)
    parser.add_argument("--prefix", help="iceoryx2 prefix (default SUPERFLOW_IOX_PREFIX)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds to wait for a batch")
    args = parser.parse_args()

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.type == "cuda":
        torch.set_default_device(device)  # the reference losses allocate without a device
    vit, _, _, head2d = ref.build("tiny", 0)
    unet = SpconvMinkUNet().to(device)
    head3d = ref.linear(unet.out_channels, ref.OUT_DIM, (1.0 / unet.out_channels) ** 0.5, True)
    head3d, head2d = head3d.to(device), head2d.to(device)
    params = [*unet.parameters(), *head3d.parameters(), *head2d.parameters()]
    opt = torch.optim.AdamW(params, lr=args.lr)
    mean = torch.tensor(ref.MEAN).view(1, 3, 1, 1)
    std = torch.tensor(ref.STD).view(1, 3, 1, 1)

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    for step, batch in enumerate(stream):
        started = time.perf_counter()
        with batch:
            arrays = {name: np.asarray(batch[name]) for name in batch.names()}
            # Copies what the losses index; spconv finds its own maps, so the batch's (if the
            # pipeline sent any: kernel_maps = "unet") are not read.
            inputs = ref.prepare(arrays, args.pixel_stride, maps_needed=False)
            x = sft.spconv_tensor(batch, device=device)  # features: the batch's memory on a CPU
            position = (batch.epoch, batch.step)
            del arrays
            with torch.no_grad():
                images = inputs["images"].permute(0, 3, 1, 2).float() / 255.0
                tokens = vit((images - mean) / std).to(device)
            pixel = head2d(tokens, to(inputs["sampler"], device))
            vox = Fn.normalize(head3d(unet(x)), dim=1)
            del x  # the batch's memory goes back with the release
        losses = ref.superflow_losses(vox[inputs["pairing_voxel"].to(device)], pixel,
                                      to(inputs["ix"], device))
        record = {"step": step, "epoch": position[0], "stream_step": position[1],
                  **{k: losses[k].item() for k in ("total", "l_sc", "l_tc", "l_d2s")}}
        if device.type != "cuda":
            print(json.dumps({**record, "forward_s": time.perf_counter() - started,
                              "stopped": "spconv's CPU build runs forward passes only (its "
                              "backward asks for CUDA): stopping after the forward pass and "
                              "the losses; train on a GPU with spconv-cu1xx"}), flush=True)
            break
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        opt.step()
        print(json.dumps({**record, "step_s": time.perf_counter() - started}), flush=True)
        if step + 1 >= args.steps:
            break
    stream.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
