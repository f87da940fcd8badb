"""PyTorch bridges for the batch's sparse voxels: ``spconv_tensor(batch, level=0)`` gives
spconv's ``SparseConvTensor`` (OpenPCDet, Pointcept) of a batch's voxels, with no copy of
the features.

    import superflow.torch
    x = superflow.torch.spconv_tensor(batch)        # pip install "./trainer/python[spconv]"

The tensor's rows are the batch's rows at that level, in order, so ``point_to_voxel``,
the pairings and ``l{l}_nbr`` / ``l{l}_down`` still index it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .stream import Batch


def spconv_coordinates(batch: Batch, level: int = 0) -> tuple[np.ndarray, list[int], int]:
    """``(indices, spatial_shape, batch_size)`` of the batch's level-``level`` voxels as
    spconv wants them: ``indices`` int32 ``V×4`` rows ``(cloud, cell)`` in the batch's
    row order, the cell shifted by its per-axis minimum so that it is non-negative;
    ``spatial_shape`` the extent of the shifted cells; ``batch_size`` the clouds of the
    batch (``B·C``: each cloud is one spconv sample). A copy (the shift)."""
    if f"l{level}_coords" not in batch:
        raise ValueError(f"the batch has no level {level} (l{level}_coords): a pipeline whose "
                         'recipe has kernel_maps = "none" sends level 0 only')
    coords = np.asarray(batch[f"l{level}_coords"])
    clouds = len(batch[f"l{level}_clouds"]) - 1
    if coords.ndim != 2 or coords.shape[1] != 4:
        raise ValueError(f"l{level}_coords has shape {coords.shape}, expected V×4")
    indices = np.array(coords, dtype=np.int32)
    if len(indices):
        low = indices[:, 1:].min(axis=0)
        indices[:, 1:] -= low
        shape = [int(s) + 1 for s in indices[:, 1:].max(axis=0)]
    else:
        shape = [1, 1, 1]
    return indices, shape, clouds


def spconv_tensor(batch: Batch, level: int = 0, features: Any = None, device: Any = None) -> Any:
    """The batch's voxels at ``level`` as a ``spconv.pytorch.SparseConvTensor``:
    ``features`` (default at level 0: ``voxel_features``, x, y, z, intensity of each
    voxel's representative point, shared with the batch's memory, no copy; at other
    levels pass your own ``V_l×C`` tensor), indices from :func:`spconv_coordinates`,
    ``batch_size`` = the batch's clouds. ``device``: where to put both (a copy). The
    features keep the batch's memory while they are alive (the lifetime rule)."""
    import torch
    from spconv.pytorch import SparseConvTensor  # pip install "./trainer/python[spconv]"

    indices, shape, clouds = spconv_coordinates(batch, level)
    if features is None:
        if level != 0:
            raise ValueError(f"level {level} has no voxel features in the batch: pass features=")
        features = torch.from_numpy(np.asarray(batch["voxel_features"]))
    if features.shape[0] != len(indices):
        raise ValueError(f"{features.shape[0]} feature rows for the {len(indices)} voxels of "
                         f"level {level}")
    index_tensor = torch.from_numpy(indices)
    if device is not None:
        features, index_tensor = features.to(device), index_tensor.to(device)
    return SparseConvTensor(features, index_tensor, shape, clouds)
