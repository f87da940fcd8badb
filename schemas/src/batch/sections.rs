//! The sections of a SuperFlow batch: the one table of every section's name, dtype,
//! symbolic shape and meaning. The pipeline plans and writes a batch through it, the
//! trainer reads through it, and `schemas/BATCH_FORMAT.md` shows it as rendered by
//! [`markdown`] (a test keeps the two equal).
//!
//! Per-level sections are named `l{l}_<part>` and addressed as, e.g.,
//! `Section::LevelNbr(l)`; [`Section::in_order`] lists the sections of a batch in payload
//! order, and [`Dims::shape`] turns a section's symbolic shape into numbers.

use super::error::BatchError;
use super::format::{DType, Element};
use std::borrow::Cow;

/// One row of the table.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SectionSpec {
    /// The name; `l{l}_...` for the per-level sections (see [`Section::name`]).
    pub name: &'static str,
    /// Element type.
    pub dtype: DType,
    /// Dimensions, outermost first, in the symbols of [`SYMBOLS`] (`·` multiplies);
    /// digits are fixed sizes.
    pub shape: &'static [&'static str],
    /// What the section holds.
    pub meaning: &'static str,
}

/// The symbols of the shapes, with what they count.
pub const SYMBOLS: &[(&str, &str)] = &[
    ("B", "samples in the batch"),
    ("F", "temporal frames per sample"),
    (
        "S",
        "camera slots of the batch: the cameras of every sample, `K_b` for sample `b`",
    ),
    (
        "C",
        "clouds per sample, `F + 1`: the frames in time order, then the dense cloud",
    ),
    ("H", "image height after resizing"),
    ("W", "image width after resizing"),
    ("N", "points of all clouds"),
    ("P", "point–pixel pairings of all clouds"),
    ("V₀", "level-0 voxels of all clouds"),
    ("V_l", "voxels of all clouds at UNet level `l` (stride 2^l)"),
    ("E", "pairs of the neighbour map of level `l`"),
    ("L", "UNet levels: `l` runs over `0..L`"),
];

/// A section of a SuperFlow batch; its row of the table is [`Section::spec`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Section {
    /// `sample_ids`.
    SampleIds,
    /// `frame_stamps`.
    FrameStamps,
    /// `frame_offsets`.
    FrameOffsets,
    /// `camera_ids`.
    CameraIds,
    /// `sample_cameras`.
    SampleCameras,
    /// `image_stamps`.
    ImageStamps,
    /// `image_flipped`.
    ImageFlipped,
    /// `images`.
    Images,
    /// `superpixels`.
    Superpixels,
    /// `num_superpixels`.
    NumSuperpixels,
    /// `points`.
    Points,
    /// `point_clouds`.
    PointClouds,
    /// `source_sweep`.
    SourceSweep,
    /// `point_to_voxel`.
    PointToVoxel,
    /// `augmentation`.
    Augmentation,
    /// `pairing_point`.
    PairingPoint,
    /// `pairing_image`.
    PairingImage,
    /// `pairing_pixel`.
    PairingPixel,
    /// `pairing_uv`.
    PairingUv,
    /// `pairing_depth`.
    PairingDepth,
    /// `pairing_superpixel`.
    PairingSuperpixel,
    /// `pairing_clouds`.
    PairingClouds,
    /// `voxel_features`.
    VoxelFeatures,
    /// `l{l}_coords`.
    LevelCoords(usize),
    /// `l{l}_clouds`.
    LevelClouds(usize),
    /// `l{l}_nbr`.
    LevelNbr(usize),
    /// `l{l}_nbr_starts`.
    LevelNbrStarts(usize),
    /// `l{l}_down`.
    LevelDown(usize),
    /// `l{l}_down_starts`.
    LevelDownStarts(usize),
}

const fn spec(
    name: &'static str,
    dtype: DType,
    shape: &'static [&'static str],
    meaning: &'static str,
) -> SectionSpec {
    SectionSpec {
        name,
        dtype,
        shape,
        meaning,
    }
}

use DType::{F32, I32, I64, U8, U16, U32, U64};

/// The table, in payload order: the sections of every batch, then those of each level.
const TABLE: [SectionSpec; 29] = [
    spec(
        "sample_ids",
        U64,
        &["B", "5"],
        "epoch, index in epoch, keyframe, drive, sweep",
    ),
    spec(
        "frame_stamps",
        I64,
        &["B", "F"],
        "LiDAR stamp of each frame, ns",
    ),
    spec(
        "frame_offsets",
        I32,
        &["F"],
        "frame offsets in units of Δt (−1, 0, 1)",
    ),
    spec(
        "camera_ids",
        U32,
        &["S"],
        "camera index in its drive, per camera slot",
    ),
    spec(
        "sample_cameras",
        U32,
        &["B+1"],
        "first camera slot of each sample: `K_b = sample_cameras[b+1] − sample_cameras[b]`",
    ),
    spec("image_stamps", I64, &["F·S"], "image stamps, ns"),
    spec("image_flipped", U8, &["F·S"], "1 if the image was mirrored"),
    spec("images", U8, &["F·S", "H", "W", "3"], "RGB, resized"),
    spec(
        "superpixels",
        U16,
        &["F·S", "H", "W"],
        "superpixel id per pixel (ids per frame)",
    ),
    spec(
        "num_superpixels",
        U32,
        &["B", "F"],
        "ids of frame (b, f) are `0..n`",
    ),
    spec("points", F32, &["N", "4"], "x, y, z (augmented), intensity"),
    spec(
        "point_clouds",
        U32,
        &["B·C+1"],
        "first point row of each cloud",
    ),
    spec(
        "source_sweep",
        U8,
        &["N"],
        "0 = keyframe sweep, k = k-th earlier (dense cloud)",
    ),
    spec(
        "point_to_voxel",
        U32,
        &["N"],
        "level-0 voxel row of each point",
    ),
    spec(
        "augmentation",
        F32,
        &["B·C", "4"],
        "flip_x, flip_y, yaw (rad), scale",
    ),
    spec("pairing_point", U32, &["P"], "point row"),
    spec("pairing_image", U32, &["P"], "image number"),
    spec(
        "pairing_pixel",
        U16,
        &["P", "2"],
        "(row, col) in the resized image",
    ),
    spec("pairing_uv", F32, &["P", "2"], "(u, v) in the raw image"),
    spec("pairing_depth", F32, &["P"], "depth, m"),
    spec(
        "pairing_superpixel",
        U32,
        &["P"],
        "superpixel id (of the frame) of the pixel",
    ),
    spec(
        "pairing_clouds",
        U32,
        &["B·C+1"],
        "first pairing of each cloud",
    ),
    spec(
        "voxel_features",
        F32,
        &["V₀", "4"],
        "representative point's x, y, z, intensity",
    ),
    spec(
        "l{l}_coords",
        I32,
        &["V_l", "4"],
        "cloud, then the cell at level l (stride 2^l)",
    ),
    spec(
        "l{l}_clouds",
        U32,
        &["B·C+1"],
        "first voxel row of each cloud at level l",
    ),
    spec(
        "l{l}_nbr",
        U32,
        &["E", "2"],
        "3×3×3 map (input row, output row), offset by offset",
    ),
    spec(
        "l{l}_nbr_starts",
        U32,
        &["28"],
        "pairs of offset k are `nbr[starts[k]..starts[k+1]]`",
    ),
    spec(
        "l{l}_down",
        U32,
        &["V_l", "2"],
        "stride-2 map (row at l, row at l+1); transpose = up; levels l < L−1 only",
    ),
    spec(
        "l{l}_down_starts",
        U32,
        &["9"],
        "pairs of child position k; levels l < L−1 only",
    ),
];

impl Section {
    /// The sections of every batch, in payload order (the per-level ones follow).
    pub const BATCH: [Section; 23] = [
        Section::SampleIds,
        Section::FrameStamps,
        Section::FrameOffsets,
        Section::CameraIds,
        Section::SampleCameras,
        Section::ImageStamps,
        Section::ImageFlipped,
        Section::Images,
        Section::Superpixels,
        Section::NumSuperpixels,
        Section::Points,
        Section::PointClouds,
        Section::SourceSweep,
        Section::PointToVoxel,
        Section::Augmentation,
        Section::PairingPoint,
        Section::PairingImage,
        Section::PairingPixel,
        Section::PairingUv,
        Section::PairingDepth,
        Section::PairingSuperpixel,
        Section::PairingClouds,
        Section::VoxelFeatures,
    ];

    /// The sections of level `l`, in payload order; the last two (`down`) exist only
    /// below the coarsest level.
    pub const fn of_level(l: usize) -> [Section; 6] {
        [
            Section::LevelCoords(l),
            Section::LevelClouds(l),
            Section::LevelNbr(l),
            Section::LevelNbrStarts(l),
            Section::LevelDown(l),
            Section::LevelDownStarts(l),
        ]
    }

    /// Every section of a batch with `levels` UNet levels, in payload order.
    pub fn in_order(levels: usize) -> impl Iterator<Item = Section> {
        let per_level = (0..levels).flat_map(move |l| {
            let parts = if l + 1 < levels { 6 } else { 4 };
            Section::of_level(l).into_iter().take(parts)
        });
        Section::BATCH.into_iter().chain(per_level)
    }

    /// Every section of a batch that carries level 0's voxels and no kernel map (a recipe
    /// with `kernel_maps = "none"`, for a 3D network that builds its own maps), in payload
    /// order: `l0_coords` and `l0_clouds` after the batch's sections.
    pub fn in_order_unmapped() -> impl Iterator<Item = Section> {
        let cells = Section::of_level(0).into_iter().take(2);
        Section::BATCH.into_iter().chain(cells)
    }

    /// The section's row of the table.
    pub const fn spec(self) -> &'static SectionSpec {
        let index = match self {
            Section::SampleIds => 0,
            Section::FrameStamps => 1,
            Section::FrameOffsets => 2,
            Section::CameraIds => 3,
            Section::SampleCameras => 4,
            Section::ImageStamps => 5,
            Section::ImageFlipped => 6,
            Section::Images => 7,
            Section::Superpixels => 8,
            Section::NumSuperpixels => 9,
            Section::Points => 10,
            Section::PointClouds => 11,
            Section::SourceSweep => 12,
            Section::PointToVoxel => 13,
            Section::Augmentation => 14,
            Section::PairingPoint => 15,
            Section::PairingImage => 16,
            Section::PairingPixel => 17,
            Section::PairingUv => 18,
            Section::PairingDepth => 19,
            Section::PairingSuperpixel => 20,
            Section::PairingClouds => 21,
            Section::VoxelFeatures => 22,
            Section::LevelCoords(_) => 23,
            Section::LevelClouds(_) => 24,
            Section::LevelNbr(_) => 25,
            Section::LevelNbrStarts(_) => 26,
            Section::LevelDown(_) => 27,
            Section::LevelDownStarts(_) => 28,
        };
        &TABLE[index]
    }

    /// The UNet level of a per-level section.
    pub const fn level(self) -> Option<usize> {
        match self {
            Section::LevelCoords(l)
            | Section::LevelClouds(l)
            | Section::LevelNbr(l)
            | Section::LevelNbrStarts(l)
            | Section::LevelDown(l)
            | Section::LevelDownStarts(l) => Some(l),
            _ => None,
        }
    }

    /// The name in the batch: the table's, with the level filled in (`l2_nbr`).
    pub fn name(self) -> Cow<'static, str> {
        match self.level() {
            None => Cow::Borrowed(self.spec().name),
            Some(l) => Cow::Owned(self.spec().name.replace("{l}", &l.to_string())),
        }
    }

    /// The section of a name found in a batch, if the table has it.
    pub fn parse(name: &str) -> Option<Section> {
        if let Some(section) = Section::BATCH.into_iter().find(|s| s.spec().name == name) {
            return Some(section);
        }
        let (digits, part) = name.strip_prefix('l')?.split_once('_')?;
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        // Reject leading zeros, so that a name has one spelling.
        let l: usize = digits
            .parse()
            .ok()
            .filter(|l: &usize| l.to_string() == digits)?;
        Section::of_level(l)
            .into_iter()
            .find(|s| s.spec().name.strip_prefix("l{l}_") == Some(part))
    }

    /// An error unless the table declares the section with element type `T`.
    pub fn check<T: Element>(self) -> Result<(), BatchError> {
        let spec = self.spec();
        if spec.dtype == T::DTYPE {
            return Ok(());
        }
        Err(BatchError::NotAsDeclared {
            name: self.name().into_owned(),
            reason: format!(
                "accessed as {:?}, the section table declares {:?}",
                T::DTYPE,
                spec.dtype
            ),
        })
    }

    /// An error unless `shape` has the table's rank and fixed sizes.
    pub fn check_shape(self, shape: &[usize]) -> Result<(), BatchError> {
        let spec = self.spec();
        let fits = shape.len() == spec.shape.len()
            && spec
                .shape
                .iter()
                .zip(shape)
                .all(|(symbol, d)| symbol.parse::<usize>().map_or(true, |fixed| fixed == *d));
        if fits {
            return Ok(());
        }
        Err(BatchError::NotAsDeclared {
            name: self.name().into_owned(),
            reason: format!(
                "shape {shape:?}, the section table declares {}",
                spec.shape.join("×")
            ),
        })
    }
}

/// The sizes behind the symbols of [`SYMBOLS`], for one batch.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Dims {
    /// `B`.
    pub samples: usize,
    /// `F`.
    pub frames: usize,
    /// `S`: camera slots of all samples.
    pub camera_slots: usize,
    /// `H`.
    pub height: usize,
    /// `W`.
    pub width: usize,
    /// `N`.
    pub points: usize,
    /// `P`.
    pub pairings: usize,
    /// `V₀`.
    pub voxels: usize,
    /// `(V_l, E)` of every level `l`; `L` is the length.
    pub levels: Vec<LevelDims>,
}

/// The sizes of one UNet level.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LevelDims {
    /// `V_l`: voxels at the level.
    pub voxels: usize,
    /// `E`: pairs of the level's neighbour map.
    pub pairs: usize,
}

impl Dims {
    /// The shape of `section`: its table shape with the symbols replaced by these sizes.
    pub fn shape(&self, section: Section) -> Result<Vec<usize>, BatchError> {
        let level = section.level().unwrap_or(0);
        let unknown = |what: &str| BatchError::NotAsDeclared {
            name: section.name().into_owned(),
            reason: format!("no size for `{what}` in its shape"),
        };
        let level_dims = |l: usize| self.levels.get(l).ok_or_else(|| unknown("level"));
        let value = |symbol: &str| -> Result<usize, BatchError> {
            Ok(match symbol {
                "B" => self.samples,
                "F" => self.frames,
                "S" => self.camera_slots,
                "C" => self.frames + 1,
                "H" => self.height,
                "W" => self.width,
                "N" => self.points,
                "P" => self.pairings,
                "V₀" => self.voxels,
                "V_l" => level_dims(level)?.voxels,
                "E" => level_dims(level)?.pairs,
                "L" => self.levels.len(),
                fixed => fixed.parse().map_err(|_| unknown(fixed))?,
            })
        };
        let evaluate = |expression: &str| -> Result<usize, BatchError> {
            expression.split('+').try_fold(0, |sum, term| {
                let product = term.split('·').map(value).product::<Result<usize, _>>()?;
                Ok(sum + product)
            })
        };
        section.spec().shape.iter().map(|e| evaluate(e)).collect()
    }
}

/// The section table as `BATCH_FORMAT.md` shows it: the symbols, then one row per section.
pub fn markdown() -> String {
    let mut out = String::from("| symbol | counts |\n|---|---|\n");
    for (symbol, meaning) in SYMBOLS {
        out += &format!("| {symbol} | {meaning} |\n");
    }
    out += "\n| section | dtype | numpy | shape | meaning |\n|---|---|---|---|---|\n";
    for spec in &TABLE {
        out += &format!(
            "| `{}` | {} | `{}` | {} | {} |\n",
            spec.name,
            spec.dtype.name(),
            spec.dtype.numpy(),
            spec.shape.join("×"),
            spec.meaning
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A batch without maps is a batch with them cut before `l0_nbr`, for any level count.
    #[test]
    fn the_unmapped_sections_begin_every_mapped_batch() {
        let unmapped: Vec<Section> = Section::in_order_unmapped().collect();
        assert_eq!(unmapped.len(), 23 + 2);
        assert_eq!(
            unmapped[23..],
            [Section::LevelCoords(0), Section::LevelClouds(0)]
        );
        for levels in 1..=8 {
            let mapped: Vec<Section> = Section::in_order(levels).collect();
            assert_eq!(mapped[..unmapped.len()], unmapped[..]);
            assert_eq!(mapped[unmapped.len()], Section::LevelNbr(0));
        }
    }

    #[test]
    fn every_section_has_its_row_and_parses_back() {
        let all: Vec<Section> = Section::in_order(3).collect();
        assert_eq!(all.len(), 23 + 6 + 6 + 4);
        let rows: Vec<&str> = Section::BATCH
            .into_iter()
            .chain(Section::of_level(0))
            .map(|s| s.spec().name)
            .collect();
        let table: Vec<&str> = TABLE.iter().map(|s| s.name).collect();
        assert_eq!(rows, table);
        for section in Section::in_order(12) {
            assert_eq!(Section::parse(&section.name()), Some(section));
        }
        assert_eq!(Section::LevelNbr(2).name(), "l2_nbr");
        assert_eq!(Section::parse("l02_nbr"), None);
        assert_eq!(Section::parse("l_nbr"), None);
        assert_eq!(Section::parse("l1_nbrs"), None);
        assert_eq!(Section::parse("voxel_coords"), None);
    }

    #[test]
    fn every_symbol_is_known_and_every_shape_evaluates() {
        let dims = Dims {
            samples: 2,
            frames: 3,
            camera_slots: 5,
            height: 7,
            width: 11,
            points: 13,
            pairings: 17,
            voxels: 19,
            levels: vec![LevelDims {
                voxels: 23,
                pairs: 29,
            }],
        };
        for spec in &TABLE {
            for dim in spec.shape {
                for factor in dim.split(['+', '·']) {
                    assert!(
                        factor.parse::<usize>().is_ok()
                            || SYMBOLS.iter().any(|(s, _)| *s == factor),
                        "{}: {factor}",
                        spec.name
                    );
                }
            }
        }
        assert_eq!(dims.shape(Section::Images).unwrap(), [15, 7, 11, 3]);
        assert_eq!(dims.shape(Section::SampleCameras).unwrap(), [3]);
        assert_eq!(dims.shape(Section::PointClouds).unwrap(), [9]);
        assert_eq!(dims.shape(Section::Augmentation).unwrap(), [8, 4]);
        assert_eq!(dims.shape(Section::LevelNbr(0)).unwrap(), [29, 2]);
        assert_eq!(dims.shape(Section::LevelDown(0)).unwrap(), [23, 2]);
        assert!(dims.shape(Section::LevelCoords(1)).is_err());
        for section in Section::in_order(1) {
            let shape = dims.shape(section).unwrap();
            section.check_shape(&shape).unwrap();
        }
    }

    #[test]
    fn accesses_are_checked_against_the_table() {
        assert!(Section::PairingPoint.check::<u32>().is_ok());
        let err = Section::LevelNbr(3).check::<u16>().unwrap_err();
        assert_eq!(
            err.to_string(),
            "section `l3_nbr`: accessed as U16, the section table declares U32"
        );
        assert!(Section::SampleIds.check_shape(&[4, 5]).is_ok());
        assert!(Section::SampleIds.check_shape(&[4, 6]).is_err());
        assert!(Section::SampleIds.check_shape(&[20]).is_err());
    }
}
