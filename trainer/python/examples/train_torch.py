"""SuperFlow pretraining in PyTorch on a superflow stream: the model and losses of the Rust
trainer (MinkUNet on the batch's own kernel maps, a frozen ViT, the 2D/3D heads and the
spatial, temporal and dense-to-sparse contrastive losses, from trainer/reference/), fed by
`superflow.Stream`, with DistributedDataParallel across ranks.

    superflow-pipeline --mcap recordings/drives --run exp1 --world-size 2 --batch-size 1 &
    torchrun --standalone --nproc-per-node 2 -- trainer/python/examples/train_torch.py --run exp1 --epochs 2

(the `--` keeps torchrun from taking `--run` for an abbreviation of its `--run-path`).
On two nodes, each runs its own pipeline on the same drives (node 1: `--host-rank 1`,
`--node-rank 1`):

    superflow-pipeline --mcap /data/drives --run exp1 --world-size 4 --host-rank 0 --host-count 2 &
    torchrun --nnodes 2 --nproc-per-node 4 --node-rank 0 --master-addr node0 --master-port 29500 \
        -- trainer/python/examples/train_torch.py --run exp1

Each rank reads its own shard (the stream ``LOCAL_RANK`` of its node's pipeline) epoch
by epoch (``stream.epoch(drop_uneven=True)``: every rank stops an epoch at the same batch count,
so the ranks stay in step and end together when the pipeline's last epoch is done, or
after ``--epochs`` / ``--steps``); gradients are averaged by DDP (gloo on CPU, nccl on
GPU). One process without torchrun reads the
broadcast stream. Prints one JSON line per step and rank: losses, the samples, and at the
end a hash of the parameters (equal on every rank when DDP keeps them in step) and the
steps per second.

Run from the repository: the model code is trainer/reference/bench_torch.py. Needs
``pip install ./trainer/python[torch] safetensors`` (the tiny ViT's weights are a
safetensors fixture).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as Fn
from torch import nn

import superflow

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "reference"))
import bench_torch as ref  # the PyTorch model and losses of the Rust trainer


class SuperFlowNet(nn.Module):
    """The trainable part: the 3D network, its head and the 2D head (the ViT is frozen)."""

    def __init__(self, unet: nn.Module, head3d: nn.Module, head2d: nn.Module):
        super().__init__()
        self.unet, self.head3d, self.head2d = unet, head3d, head2d

    def forward(self, tokens: torch.Tensor, batch: dict) -> dict:
        pixel = self.head2d(tokens, batch["sampler"])
        vox = Fn.normalize(self.head3d(self.unet(batch["voxel_features"], batch["maps"])), dim=1)
        return ref.superflow_losses(vox[batch["pairing_voxel"]], pixel, batch["ix"])


def emit(record: dict) -> None:
    """Prints `record` as one JSON line in a single write: ranks share stdout, and with
    unbuffered output (`python -u`, PYTHONUNBUFFERED) `print` writes the line and its
    newline separately, so two ranks' lines could run together."""
    sys.stdout.write(json.dumps(record) + "\n")
    sys.stdout.flush()


def params_hash(module: nn.Module) -> str:
    """A hash of every parameter (not the batch-norm statistics, which each rank keeps
    from its own last batch)."""
    digest = hashlib.sha256()
    for name, p in sorted(module.named_parameters()):
        digest.update(name.encode())
        digest.update(p.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def batches(stream: superflow.Stream, epochs: int | None, steps: int | None):
    """This rank's batches epoch by epoch, every rank the same count per epoch, until the
    stream ends (the pipeline's last epoch), or after `epochs` epochs or `steps` batches."""
    taken = 0
    epoch = 0
    while not stream.ended and (epochs is None or epoch < epochs):
        for batch in stream.epoch(drop_uneven=True):
            yield batch
            taken += 1
            if steps is not None and taken >= steps:
                return
        epoch += 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--epochs", type=int, default=None,
                        help="epochs to train (default: until the pipeline's last epoch)")
    parser.add_argument("--steps", type=int, default=None, help="stop after this many steps")
    parser.add_argument("--preset", default="tiny", choices=sorted(ref.PRESETS))
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--pixel-stride", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--prefix", help="iceoryx2 prefix (default SUPERFLOW_IOX_PREFIX)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds to wait for a batch")
    args = parser.parse_args()

    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world > 1:
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    device = (torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
              if torch.cuda.is_available() else torch.device("cpu"))
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))

    # The same seed on every rank; DDP also broadcasts rank 0's parameters at wrap time.
    vit, unet, head3d, head2d = ref.build(args.preset, args.seed)
    net = SuperFlowNet(unet, head3d, head2d).to(device)
    model = nn.parallel.DistributedDataParallel(net) if world > 1 else net
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr)
    mean = torch.tensor(ref.MEAN).view(1, 3, 1, 1)
    std = torch.tensor(ref.STD).view(1, 3, 1, 1)

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    if world > 1:
        stream.check_plan()  # every node's pipeline serves the same drives, seed and hosts
    started = time.perf_counter()
    step = -1
    last = None  # the last batch trained on: a lost batch's stand-in
    for step, batch in enumerate(batches(stream, args.epochs, args.steps)):
        with batch:
            position = (batch.epoch, batch.step, batch.sample_ids)
            lost = batch.lost
            if not lost:
                arrays = {name: np.asarray(batch[name]) for name in batch.names()}
                last = ref.prepare(arrays, args.pixel_stride)  # copies out of the shared memory
        # A lost batch (every sample failed in the pipeline) is still a step of every
        # rank, so DDP's collectives stay in step: this rank adds a zero gradient (the
        # last batch's loss times 0); with nothing to stand in, every rank skips it.
        if world > 1:
            stuck = torch.tensor([float(lost and last is None)])
            dist.all_reduce(stuck)
            if stuck.item() > 0:
                emit({"rank": rank, "step": step, "epoch": position[0],
                      "stream_step": position[1], "skipped": "lost batch"})
                continue
        elif lost:
            emit({"rank": rank, "step": step, "epoch": position[0],
                  "stream_step": position[1], "skipped": "lost batch"})
            continue
        with torch.no_grad():
            x = last["images"].permute(0, 3, 1, 2).float() / 255.0
            tokens = vit((x - mean) / std).to(device)
        losses = model(tokens, last)
        opt.zero_grad(set_to_none=True)
        (losses["total"] * (0.0 if lost else 1.0)).backward()
        opt.step()
        emit({"rank": rank, "step": step, "epoch": position[0],
              "stream_step": position[1], "sample_ids": position[2], "lost": lost,
              **{k: losses[k].item() for k in ("total", "l_sc", "l_tc", "l_d2s")}})
    elapsed = time.perf_counter() - started
    steps = step + 1
    emit({"rank": rank, "world_size": world, "steps": steps, "stream_ended": stream.ended,
          "steps_per_s": steps / elapsed, "params_hash": params_hash(net)})
    stream.close()
    if world > 1:
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
