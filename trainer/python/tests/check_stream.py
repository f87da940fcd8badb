"""Scenarios of the `superflow` Python package against a real `superflow-pipeline`, run by
`cargo test -p superflow-tests --test e2e python_package::` with the package installed in a
fresh virtual environment (as a user installs it). Each prints JSON lines and exits
non-zero when a check fails.

    check_stream.py read --run R [--count N] [--timeout S]   # one line per batch
    check_stream.py resume --run R                           # resume replays bit-identically
    check_stream.py kept --run R                             # views outlive their release
    check_stream.py epochs --run R                           # epochs that end
    check_stream.py uneven --run R                           # ranks in step on uneven shards
    check_stream.py spconv --run R                           # spconv's SparseConvTensor
    check_stream.py torch_views --run R                      # torch tensors share the memory
    check_stream.py timeout --run R --timeout S              # no pipeline: PipelineTimeout
    check_stream.py malformed --run R                        # bad batches: typed errors
    check_stream.py fleet --run R                            # an epoch of mixed rigs
    check_stream.py elastic --run R --count N [--state JSON] # state_dict / load_state_dict
    check_stream.py in_place --run R                         # in-place ops on batch tensors
    check_stream.py workers --run R                          # DataLoader workers: clear errors
    check_stream.py hosts --run R --count N                  # a rank of a multi-node job
    check_stream.py lost --run R --signal FILE               # lost batches keep epochs whole
    check_stream.py close_live --run R [--keep]              # close() with live views
    check_stream.py no_schedule --run R                      # no schedule service: typed error
    check_stream.py past_end --run R                         # resume past the end: RunComplete

`--prefix` defaults to SUPERFLOW_IOX_PREFIX; RANK / WORLD_SIZE select a shard.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import sys
import threading
import time
import warnings
from typing import Any

import numpy as np

import superflow
from superflow import format as fmt


def checksum(data: np.ndarray) -> int:
    """sum_i (b_i + 1) * (i * K + 1) mod 2^64 over the bytes (the Rust probe's too)."""
    b = np.ascontiguousarray(data).reshape(-1).view(np.uint8).astype(np.uint64) + np.uint64(1)
    weights = np.arange(b.size, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(1)
    with np.errstate(over="ignore"):
        return int(np.sum(b * weights, dtype=np.uint64))


def describe(batch: superflow.Batch, payload_range: tuple[int, int]) -> dict:
    """What a batch holds: position, samples, and every section's dtype, shape, checksum."""
    start, end = payload_range
    arrays = {name: np.asarray(batch[name]) for name in batch.names()}
    inside = all(a.size == 0 or start <= a.__array_interface__["data"][0] < end
                 for a in arrays.values())
    return {
        "sequence": batch.sequence,
        "epoch": batch.epoch,
        "step": batch.step,
        "sample_ids": batch.sample_ids,
        "keyframes": batch.keyframes,
        "zero_copy": inside and mapped_file(start).startswith("/dev/shm/"),
        "sections": {name: {"dtype": a.dtype.str.replace("|", "<"), "shape": list(a.shape),
                            "checksum": checksum(a)} for name, a in arrays.items()},
    }


def payload_range(batch: superflow.Batch) -> tuple[int, int]:
    """Where the batch's memory lies: its copy-on-write mapping of the shared memory
    (``mapped_file`` checks that it maps the pipeline's shared-memory file)."""
    return batch._mapped


def mapped_file(address: int) -> str:
    """The file this process maps at ``address`` ("" for anonymous memory)."""
    with open("/proc/self/maps") as maps:
        for line in maps:
            parts = line.split(maxsplit=5)
            low, high = (int(v, 16) for v in parts[0].split("-"))
            if low <= address < high:
                return parts[5].strip() if len(parts) > 5 else ""
    return ""


def emit(record: dict) -> None:
    print(json.dumps(record), flush=True)


def read(args: argparse.Namespace) -> int:
    """One line per batch; with --keep, views of the second batch are kept to the end and
    checked against copies made at receive (a last line)."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    kept = None
    for i in range(args.count):
        batch = next(stream)
        emit(describe(batch, payload_range(batch)))
        if args.keep and i == 1:
            view = batch["points"]
            kept = (view, np.array(view), batch)
    if kept is not None:
        view, copy, batch = kept
        emit({"kept_equal": bool(np.array_equal(view, copy)), "kept_returned": batch.returned})
    stream.close()
    return 0


def resume(args: argparse.Namespace) -> int:
    """Reads 4 batches, asks for (0, 1), and checks that the next 3 are batches 1..3 again,
    section for section."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    first = {}
    for _ in range(4):
        batch = next(stream)
        first[(batch.epoch, batch.step)] = describe(batch, payload_range(batch))["sections"]
    stream.resume(0, 1)
    again = []
    for _ in range(3):
        batch = next(stream)
        again.append((batch.epoch, batch.step))
        if first.get((batch.epoch, batch.step)) != describe(batch, payload_range(batch))["sections"]:
            emit({"resume": "differs", "at": [batch.epoch, batch.step]})
            return 1
    emit({"resume": "identical", "positions": again})
    try:
        stream.resume(10**6, 0)
        emit({"refused": False})
        return 1
    except superflow.ResumeRefused as e:
        emit({"refused": True, "message": str(e)})
    stream.close()
    return 0 if again == [(0, 1), (0, 2), (0, 3)] else 1


def kept(args: argparse.Namespace) -> int:
    """Views kept past their batch's release keep their bytes while later batches come;
    holding more than max_held raises TooManyBatchesHeld; once the views are dropped the
    batches go back and the stream goes on."""
    import torch

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    first = next(stream)
    tensors = first.torch()
    points = first["points"]
    row = points[0]
    copies = {name: t.clone() for name, t in tensors.items()}
    points_copy = np.array(points)
    with first:
        pass
    checks = {"released": first.released, "deferred": not first.returned}
    try:
        first["points"]
        checks["section of a released batch raises"] = False
    except superflow.BatchReleased:
        checks["section of a released batch raises"] = True
    positions = []
    same = []
    for _ in range(10):
        batch = next(stream)
        positions.append([batch.epoch, batch.step])
        same.append(all(torch.equal(tensors[n], copies[n]) for n in tensors)
                    and np.array_equal(points, points_copy) and np.array_equal(row, points_copy[0]))
    checks["kept bytes across 10 batches"] = all(same)
    checks["numpy ops on a kept view"] = float(points.sum()) == float(points_copy.sum())
    # The current batch's view kept too: the next receive would hold 3 of 2.
    current = batch
    images = current["images"]
    try:
        next(stream)
        checks["max_held raises"] = False
        held = []
    except superflow.TooManyBatchesHeld as e:
        held = e.held
        checks["max_held raises"] = (len(held) == 2 and list(held[0]) == [first.epoch, first.step]
                                     and str(next(iter(held[0]))) in str(e) and "del" in str(e))
    del tensors, points, row, images
    checks["returned after del"] = first.returned and current.returned and stream.held() == []
    for _ in range(3):
        batch = next(stream)
        positions.append([batch.epoch, batch.step])
    # A prefetching wrapper may drop the last view on its own thread.
    box = [batch.torch()["points"]]
    batch.release()
    deferred = not batch.returned
    worker = threading.Thread(target=box.clear)
    worker.start()
    worker.join()
    checks["returned after a drop on another thread"] = deferred and batch.returned
    emit({"checks": checks, "positions": positions, "held": [list(h) for h in held],
          "repr": repr(first)})
    stream.close()
    return 0 if all(checks.values()) else 1


def torch_views(args: argparse.Namespace) -> int:
    """`batch.torch()` shares the shared memory with the numpy views, and TorchIterable in
    a DataLoader(batch_size=None) yields those dicts batch after batch."""
    import torch

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    batch = next(stream)
    tensors = batch.torch()
    start, end = payload_range(batch)
    shared = {name: tensors[name].data_ptr() == np.asarray(batch[name]).__array_interface__["data"][0]
              for name in batch.names() if batch[name].size}
    inside = all(start <= tensors[n].data_ptr() < end for n in shared)
    equal = all(torch.equal(tensors[n], torch.from_numpy(np.array(batch[n]))) for n in shared)
    # The loop below holds two batches (its item while the next is received): these
    # tensors would be a third, past max_held.
    del tensors
    loader = torch.utils.data.DataLoader(superflow.TorchIterable(stream), batch_size=None)
    steps = []
    for i, item in enumerate(loader):
        steps.append(int(item["sample_ids"][0, 1]))
        if i == 2:
            break
    emit({"shared": all(shared.values()), "sections": len(shared), "inside": inside,
          "equal": equal, "loader_sample_ids": steps,
          "loader_types": sorted({type(v).__name__ for v in item.values()})})
    stream.close()
    return 0 if all(shared.values()) and inside and equal else 1


def epochs(args: argparse.Namespace) -> int:
    """On a pipeline with --epochs 2: stream.epoch() twice, then the stream has ended;
    rewound, `for batch in stream` stops by itself after epoch 1; rewound again,
    TorchIterable in a DataLoader gives one epoch per iter(), the same batches."""
    import torch

    stream = superflow.Stream(args.run, prefix=args.prefix)  # no timeout_s: nothing to wait out
    length = len(stream.epoch())
    per_epoch = []
    for _ in range(2):
        per_epoch.append([[b.epoch, b.step, b.keyframes] for b in stream.epoch()])
    ended = stream.ended
    after = [b.step for b in stream]  # nothing: the stream ended
    stream.resume(0, 0)
    whole = [[b.epoch, b.step, b.keyframes] for b in stream]
    dataset = superflow.TorchIterable(stream)
    loader = torch.utils.data.DataLoader(dataset, batch_size=None)
    dataset.set_epoch(0)  # the stream ended at epoch 2: back to 0
    # Broken out of after one batch, the next iter() continues the same epoch.
    first_of_epoch = [int(x) for x in next(iter(loader))["sample_ids"][:, 2]]
    rest_of_epoch = [[int(x) for x in item["sample_ids"][:, 2]] for item in loader]
    dataset.set_epoch(0)  # at epoch 1 now: back to 0
    loaded = []
    for e in range(3):
        dataset.set_epoch(e)  # at e already: nothing happens
        loaded.append([[int(x) for x in item["sample_ids"][:, 2]] for item in loader])
    emit({"len": length, "loader_len": len(loader), "epochs": per_epoch, "ended": ended,
          "after_end": after, "whole": whole, "loaded": loaded,
          "continued": [first_of_epoch, *rest_of_epoch]})
    stream.close()
    return 0


def _refused(call: Any, words: str) -> bool:
    """Whether ``call()`` raises a ValueError whose text holds ``words``."""
    try:
        call()
    except ValueError as e:
        return words in str(e)
    return False


def spconv(args: argparse.Namespace) -> int:
    """superflow.torch.spconv_tensor of a batch: indices equal the batch's coordinates
    (shifted), rows in order, features shared with the batch; a SubMConv3d forward on it
    (CPU spconv runs forward only) keeps the rows."""
    import spconv.pytorch as sp
    import torch

    import superflow.torch as sft

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    batch = next(stream)
    x = sft.spconv_tensor(batch)
    coords = np.asarray(batch["l0_coords"])
    low = coords[:, 1:].min(axis=0)
    indices = x.indices.numpy()
    torch.manual_seed(0)
    conv = sp.SubMConv3d(4, 8, 3, bias=False, indice_key="subm0")
    with torch.no_grad():
        y = conv(x)
    checks = {
        "indices": bool(np.array_equal(indices[:, 0], coords[:, 0])
                        and np.array_equal(indices[:, 1:], coords[:, 1:] - low)),
        "non-negative": bool((indices >= 0).all()),
        "spatial shape": list(x.spatial_shape) == [int(v) + 1 for v in (coords[:, 1:] - low).max(axis=0)],
        "batch size = clouds": x.batch_size == len(batch["l0_clouds"]) - 1,
        "features shared": x.features.data_ptr() == np.asarray(batch["voxel_features"]).__array_interface__["data"][0],
        "forward rows": tuple(y.features.shape) == (len(coords), 8),
        "forward indices": bool(torch.equal(y.indices, x.indices)),
        "forward finite": bool(torch.isfinite(y.features).all()),
        # Run with kernel_maps = "none": level 0's voxels, no map, no coarser level, and
        # asking for one says why.
        "no maps": not any(name.endswith(("_nbr", "_down")) or name.startswith("l1_")
                           for name in batch.names())
        and _refused(lambda: sft.spconv_coordinates(batch, 1), "kernel_maps"),
    }
    emit({"checks": checks, "voxels": len(coords), "clouds": x.batch_size,
          "spatial_shape": list(x.spatial_shape)})
    stream.close()
    return 0 if all(checks.values()) else 1


def uneven(args: argparse.Namespace) -> int:
    """One rank of a pipeline whose shards differ by a batch: stream.epoch(drop_uneven=True)
    gives every rank the fewest batches per epoch; the stream ends all the same."""
    stream = superflow.Stream(args.run, prefix=args.prefix)
    schedule = stream.schedule()
    lengths = [len(stream.epoch()), len(stream.epoch(drop_uneven=True))]
    epochs = []
    while not stream.ended:
        epochs.append([[b.epoch, b.step] for b in stream.epoch(drop_uneven=True)])
    emit({"rank": stream.rank, "steps": schedule.steps, "min_steps": schedule.min_steps,
          "epochs_served": schedule.epochs, "lengths": lengths, "epochs": epochs})
    stream.close()
    return 0


def timeout(args: argparse.Namespace) -> int:
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    started = time.monotonic()
    try:
        next(stream)
    except superflow.PipelineTimeout as e:
        waited = time.monotonic() - started
        emit({"timeout": True, "waited_s": waited, "message": str(e), "run": e.run,
              "service": e.service})
        return 0 if args.timeout <= waited < args.timeout + 2 else 1
    emit({"timeout": False})
    return 1


def _header(sections: list[tuple[str, int, tuple[int, ...], int, int]], payload_len: int,
            version: int = fmt.VERSION, run: str = "bad") -> bytes:
    """A batch header with `sections` (name, dtype code, shape, offset, length)."""
    h = np.zeros(1, dtype=fmt.HEADER)
    h["magic"], h["version"], h["header_size"] = fmt.MAGIC, version, fmt.HEADER_SIZE
    h["section_count"], h["payload_len"], h["sample_count"] = len(sections), payload_len, 0
    h["run"] = run.encode()
    for i, (name, code, shape, offset, length) in enumerate(sections):
        s = h["sections"][0][i]
        s["name"], s["dtype"], s["ndim"], s["offset"], s["len_bytes"] = (
            name.encode(), code, len(shape), offset, length)
        s["shape"][:len(shape)] = shape
    return h.tobytes()


def malformed(args: argparse.Namespace) -> int:
    """Publishes bad batches on the run's broadcast service itself and checks the typed
    errors, then a good one, which the stream still reads."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    # The stream's own service and ready event, with a publisher and a notifier added.
    publisher = stream._batches.publisher_builder().initial_max_slice_len(64).create()
    notifier = stream._ready.notifier_builder().create()

    def publish(header: bytes, payload: bytes) -> None:
        sample = publisher.loan_slice_uninit(len(payload))
        ctypes.memmove(ctypes.addressof(sample.user_header().contents), header, len(header))
        ctypes.memmove(sample.payload_ptr, payload, len(payload))
        sample.assume_init().send()
        notifier.notify()

    points = np.arange(8, dtype="<f4").tobytes()
    cases = {
        # A batch of the layout before mixed rigs (every sample K cameras).
        "version 1": (_header([("points", 7, (2, 4), 0, 32)], 64, version=1),
                      superflow.FormatVersionMismatch),
        "overlapping sections": (_header([("points", 7, (2, 4), 0, 32),
                                          ("pairing_depth", 7, (8,), 0, 32)], 64),
                                 superflow.MalformedBatch),
        "dtype against the table": (_header([("points", 3, (2, 4), 0, 32)], 64),
                                    superflow.MalformedBatch),
        "unknown section": (_header([("pointz", 7, (2, 4), 0, 32)], 64),
                            superflow.MalformedBatch),
    }
    results = {}
    for what, (header, error) in cases.items():
        publish(header, points + bytes(32))
        try:
            next(stream)
            results[what] = "accepted"
        except error as e:
            ok = e.run == args.run and e.service == stream.service and args.run in str(e)
            results[what] = type(e).__name__ if ok else f"unnamed: {e}"
    publish(_header([("points", 7, (2, 4), 0, 32)], 64, run=args.run), points + bytes(32))
    good = next(stream)
    results["good batch"] = np.asarray(good["points"]).reshape(-1).tolist()
    emit(results)
    stream.close()
    expected = {"version 1": "FormatVersionMismatch", "overlapping sections": "MalformedBatch",
                "dtype against the table": "MalformedBatch", "unknown section": "MalformedBatch",
                "good batch": list(map(float, range(8)))}
    return 0 if results == expected else 1


def fleet(args: argparse.Namespace) -> int:
    """One epoch of a dataset of several rigs: each sample has its own cameras (never an
    empty image), ``sample_images`` views them, every pairing of a sample's clouds names
    one of its images, and torch tensors and spconv tensors take the batch as it is."""
    import torch

    import superflow.torch as sft

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    frames = None
    samples = []
    ok = True
    for batch in stream.epoch():
        frames = len(batch["frame_offsets"])
        slots = np.asarray(batch["sample_cameras"]).astype(np.int64)
        images = batch["images"]
        ok &= images.shape[0] == frames * int(slots[-1]) and len(batch.cameras) == len(slots) - 1
        clouds = np.asarray(batch["pairing_clouds"]).astype(np.int64)
        pairing_image = np.asarray(batch["pairing_image"])
        per_sample = frames + 1
        for b, k in enumerate(batch.cameras):
            view = batch.sample_images(b)
            ok &= view.shape == (frames, k, *images.shape[1:])
            ok &= bool(np.shares_memory(view, images))
            first = batch.image_index(b, 0, 0)
            mine = pairing_image[clouds[b * per_sample]:clouds[(b + 1) * per_sample]]
            ok &= bool(((mine >= first) & (mine < first + frames * k)).all())
            # Every image row is a camera image: no all-zero slot.
            ok &= bool(all(view[f, c].any() for f in range(frames) for c in range(k)))
            ids = batch["sample_ids"][b]
            samples.append({"drive": int(ids[3]), "keyframe": int(ids[2]), "cameras": k})
        tensors = batch.torch()
        ok &= tuple(tensors["images"].shape) == tuple(images.shape)
        x = sft.spconv_tensor(batch)
        ok &= x.features.shape[0] == batch["l0_coords"].shape[0]
        del tensors, x, view, images
    try:
        batch.image_index(0, 0, 99)
        ok = False
    except IndexError:
        pass
    emit({"ok": bool(ok), "frames": frames, "samples": samples, "torch": torch.__version__})
    stream.close()
    return 0 if ok else 1


def elastic(args: argparse.Namespace) -> int:
    """A rank of a data-parallel job: with --state, continue where a job of any size
    stopped (``load_state_dict``); read this rank's --count batches (0: the rest of the
    epoch); print the samples read and the ``state_dict`` to resume from."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    if args.state:
        stream.load_state_dict(json.loads(args.state))
    samples = []
    batches = stream.epoch() if args.count == 0 else (next(stream) for _ in range(args.count))
    for batch in batches:
        ids = batch["sample_ids"]
        samples.extend([int(i[1]), int(i[3]), int(i[2])] for i in ids)
    emit({"samples": samples, "state": stream.state_dict()})
    stream.close()
    return 0


def _smaps_private_dirty(low: int) -> int:
    """Private_Dirty bytes of this process's mapping that starts at or holds ``low``."""
    inside = False
    with open("/proc/self/smaps") as smaps:
        for line in smaps:
            head = line.split()
            if head and "-" in head[0] and len(head) >= 5 and ":" in head[3]:
                a, b = (int(v, 16) for v in head[0].split("-"))
                inside = a <= low < b
            elif inside and line.startswith("Private_Dirty:"):
                return int(head[1]) * 1024
    return -1


def in_place(args: argparse.Namespace) -> int:
    """The in-place habits on a batch's tensors and arrays: they work, change only this
    process's pages (the checksums of the untouched bytes, printed, equal another
    reader's), and copy about the bytes written, no more."""
    import torch

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    batch = next(stream)
    pristine = {name: checksum(np.asarray(batch[name])) for name in batch.names()}
    dirty_before = _smaps_private_dirty(batch._mapped[0])
    tensors = batch.torch()
    images, points = tensors["images"], tensors["points"]
    expected_images = images.clone().sub_(3)
    expected_points = points.clone()
    expected_points.mul_(2.0)
    expected_points[:, :3] -= 1.0
    expected_points[:, 1].neg_()
    # The habits: normalise / shift in place, and a flip augmentation in place.
    images.sub_(3)
    points.mul_(2.0)
    points[:, :3] -= 1.0
    points[:, 1].neg_()
    # numpy in place on another section.
    depth = batch["pairing_depth"]
    expected_depth = np.array(depth) * 0.5
    depth *= 0.5
    written = images.numel() + points.numel() * 4 + depth.nbytes
    dirty = _smaps_private_dirty(batch._mapped[0])
    checks = {
        "images": bool(torch.equal(images, expected_images)),
        "points": bool(torch.equal(points, expected_points)),
        "numpy": bool(np.array_equal(depth, expected_depth)),
        "same memory": images.data_ptr() == np.asarray(batch["images"]).__array_interface__["data"][0],
        "nothing copied before writing": dirty_before == 0,
        # Whole pages around each section, at most a page more per section edge.
        "copied about what was written": written <= dirty <= written + 6 * 4096,
    }
    del tensors, images, points, depth
    second = next(stream)  # the first goes back to the pipeline (its pages drop)
    emit({"checks": checks, "pristine": pristine, "written": written, "dirty": dirty,
          "sequence": batch.sequence, "next": [second.epoch, second.step],
          "returned": batch.returned})
    stream.close()
    return 0 if all(checks.values()) else 1


def workers(args: argparse.Namespace) -> int:
    """DataLoader workers: 2 and 4 forked workers raise WorkersUnsupported in the main
    process, spawn and forkserver StreamNotPicklable; then num_workers=0 (pin_memory=True)
    reads the whole epoch, every batch once, from the same stream."""
    import multiprocessing
    import pickle

    import torch

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    dataset = superflow.TorchIterable(stream)
    outcomes = {}
    cases = [(2, "fork"), (4, "fork"), (2, "spawn"), (2, "forkserver")]
    for workers, method in cases:
        loader = torch.utils.data.DataLoader(
            dataset, batch_size=None, num_workers=workers,
            multiprocessing_context=multiprocessing.get_context(method))
        try:
            for _ in loader:
                pass
            outcomes[f"{workers} {method}"] = "iterated"
        except (superflow.WorkersUnsupported, superflow.StreamNotPicklable) as e:
            outcomes[f"{workers} {method}"] = [type(e).__name__, "num_workers=0" in str(e)]
        del loader
        gc.collect()  # the failed iterator, before the next fork copies it
    try:
        pickle.dumps(stream)
        outcomes["pickle"] = "pickled"
    except superflow.StreamNotPicklable as e:
        outcomes["pickle"] = [type(e).__name__, isinstance(e, TypeError), args.run in str(e)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pin_memory without an accelerator
        loader = torch.utils.data.DataLoader(dataset, batch_size=None, num_workers=0,
                                             pin_memory=True)
        length = len(loader)
        ids = [[int(i) for i in item["sample_ids"][:, 1]] for item in loader]
    emit({"outcomes": outcomes, "len": length, "batches": len(ids),
          "samples": sorted(i for b in ids for i in b)})
    stream.close()
    return 0


def hosts(args: argparse.Namespace) -> int:
    """A rank of a torchrun job over several nodes (RANK, LOCAL_RANK, WORLD_SIZE,
    LOCAL_WORLD_SIZE in the environment; this node's pipeline under its own prefix): the
    stream it finds, the plan check across ranks (torch.distributed, gloo, with
    MASTER_ADDR / MASTER_PORT), and its samples of one epoch."""
    import torch.distributed as dist

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    dist.init_process_group("gloo")
    record = {"rank": dist.get_rank(), "service": stream.service, "source": stream.shard.source}
    try:
        record["plan"] = stream.check_plan()
        samples = [[int(i[0]), int(i[1])] for b in stream.epoch() for i in b["sample_ids"]]
        record["samples"] = samples
    except superflow.PlanMismatch as e:
        record["mismatch"] = str(e)
    emit(record)
    dist.barrier()
    dist.destroy_process_group()
    stream.close()
    return 0


def lost(args: argparse.Namespace) -> int:
    """Reads one batch, waits for --signal (the drives are replaced meanwhile, so later
    samples fail), then the rest of the stream: every epoch ends, lost batches included,
    and each epoch yields len() batches."""
    import os

    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    length = len(stream.epoch())
    epochs = []
    first = True
    while not stream.ended:
        epoch = []
        for batch in stream.epoch():
            epoch.append({"step": batch.step, "lost": batch.lost, "samples": len(batch),
                          "tensors": len(batch.torch())})
            if first:
                first = False
                emit({"paused": True})
                while not os.path.exists(args.signal):
                    time.sleep(0.05)
        epochs.append(epoch)
    emit({"len": length, "epochs": epochs, "ended": stream.ended})
    stream.close()
    return 0


def close_live(args: argparse.Namespace) -> int:
    """With --keep: reads a batch, keeps a tensor and an array of it, closes the stream
    and sleeps while the views stay alive; they keep their bytes. Without: reads every
    batch of the epoch (another subscriber closed with live views must not stall it)."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    if not args.keep:
        steps = [b.step for b in stream.epoch()]
        emit({"steps": steps})
        stream.close()
        return 0
    batch = next(stream)
    tensor = batch.torch()["points"]
    array = batch["images"][0]
    copies = (tensor.clone(), np.array(array))
    stream.close()
    checks = {"closed": stream.closed, "returned at close": batch.returned}
    time.sleep(args.count)
    checks["tensor kept"] = bool((tensor == copies[0]).all())
    checks["array kept"] = bool(np.array_equal(array, copies[1]))
    tensor.add_(1)  # still this process's memory
    try:
        next(stream)
        checks["receive after close raises"] = False
    except superflow.SuperflowError:
        checks["receive after close raises"] = True
    emit({"checks": checks})
    return 0 if all(checks.values()) else 1


def no_schedule(args: argparse.Namespace) -> int:
    """A publisher without a schedule service (this process's own, as in `malformed`):
    len(stream.epoch()) and iterating stream.epoch() raise ScheduleUnavailable within a
    few seconds, naming the run and service; the batch itself is still read."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    publisher = stream._batches.publisher_builder().initial_max_slice_len(64).create()
    notifier = stream._ready.notifier_builder().create()
    points = np.arange(8, dtype="<f4").tobytes()
    header = _header([("points", 7, (2, 4), 0, 32)], 64, run=args.run)
    results = {}
    for what in ("len", "epoch"):
        started = time.monotonic()
        try:
            if what == "len":
                len(stream.epoch())
            else:
                sample = publisher.loan_slice_uninit(64)
                ctypes.memmove(ctypes.addressof(sample.user_header().contents), header, len(header))
                ctypes.memmove(sample.payload_ptr, points + bytes(32), 64)
                sample.assume_init().send()
                notifier.notify()
                for _ in stream.epoch():
                    pass
            results[what] = "no error"
        except superflow.ScheduleUnavailable as e:
            results[what] = {"error": type(e).__name__, "named": args.run in str(e)
                             and e.service == stream.service,
                             "seconds": round(time.monotonic() - started, 1)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "the stream will not end by itself"
        batch = next(stream)  # the stream itself goes on without ends
    results["batch"] = np.asarray(batch["points"]).reshape(-1).tolist()
    emit(results)
    stream.close()
    return 0


def past_end(args: argparse.Namespace) -> int:
    """On a one-epoch run: read it all, then resume at its end (the position after the
    last batch, the next epoch, and a final state_dict): RunComplete, saying so."""
    stream = superflow.Stream(args.run, prefix=args.prefix, timeout_s=args.timeout)
    steps = [b.step for b in stream.epoch()]
    state = stream.state_dict()
    results = {"steps": steps, "state": state}
    for what, call in (("step", lambda: stream.resume(0, len(steps))),
                       ("epoch", lambda: stream.resume(1, 0)),
                       ("state", lambda: stream.load_state_dict(state))):
        try:
            call()
            results[what] = "accepted"
        except superflow.RunComplete as e:
            results[what] = {"epochs": e.epochs, "message": str(e)}
    stream.resume(0, len(steps) - 1)  # the last batch itself is still there
    results["last again"] = next(stream).step
    emit(results)
    stream.close()
    return 0


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario", choices=["read", "resume", "kept", "epochs", "uneven", "spconv", "torch_views",
                                             "timeout",
                                             "malformed", "fleet", "elastic", "in_place", "workers",
                                             "hosts", "lost", "close_live", "no_schedule",
                                             "past_end"])
    parser.add_argument("--state", help="elastic: a state_dict (JSON) to resume from")
    parser.add_argument("--run", required=True)
    parser.add_argument("--prefix")
    parser.add_argument("--count", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=120.0)
    parser.add_argument("--keep", action="store_true")
    parser.add_argument("--signal", help="lost: a file whose existence lets it go on")
    args = parser.parse_args()
    return globals()[args.scenario](args)


if __name__ == "__main__":
    sys.exit(main())
