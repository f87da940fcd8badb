"""The sections of a SuperFlow batch: name and numpy dtype of each, as the Rust table
(`schemas/src/batch/sections.rs`, rendered in schemas/BATCH_FORMAT.md) defines them.
`cargo test -p superflow-schemas --test batch_sections` keeps this file equal to it.

Per-level sections are named ``l{l}_<part>``: ``l0_nbr`` is the 3×3×3 neighbour map of
level 0. The last level has no ``down`` map.
"""

from __future__ import annotations

import re

import numpy as np

# name: dtype, in payload order.
BATCH_SECTIONS: dict[str, str] = {
    "sample_ids": "<u8",
    "frame_stamps": "<i8",
    "frame_offsets": "<i4",
    "camera_ids": "<u4",
    "sample_cameras": "<u4",
    "image_stamps": "<i8",
    "image_flipped": "<u1",
    "images": "<u1",
    "superpixels": "<u2",
    "num_superpixels": "<u4",
    "points": "<f4",
    "point_clouds": "<u4",
    "source_sweep": "<u1",
    "point_to_voxel": "<u4",
    "augmentation": "<f4",
    "pairing_point": "<u4",
    "pairing_image": "<u4",
    "pairing_pixel": "<u2",
    "pairing_uv": "<f4",
    "pairing_depth": "<f4",
    "pairing_superpixel": "<u4",
    "pairing_clouds": "<u4",
    "voxel_features": "<f4",
}

# part: dtype of the per-level sections `l{l}_<part>`, in payload order.
LEVEL_SECTIONS: dict[str, str] = {
    "coords": "<i4",
    "clouds": "<u4",
    "nbr": "<u4",
    "nbr_starts": "<u4",
    "down": "<u4",
    "down_starts": "<u4",
}

_LEVEL_NAME = re.compile(r"l(0|[1-9][0-9]*)_([a-z_]+)")


def section_dtype(name: str) -> np.dtype | None:
    """The dtype the format gives section `name`, or None if the table has no such name
    (a level number has one spelling: ``l01_nbr`` is not a section)."""
    if name in BATCH_SECTIONS:
        return np.dtype(BATCH_SECTIONS[name])
    match = _LEVEL_NAME.fullmatch(name)
    if match and match.group(2) in LEVEL_SECTIONS:
        return np.dtype(LEVEL_SECTIONS[match.group(2)])
    return None
