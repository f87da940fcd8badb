//! Point cloud field layouts (being written).
