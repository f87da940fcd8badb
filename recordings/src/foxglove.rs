//! Writes a simulated drive as the nuScenes converter does (2024 layout, Foxglove
//! protobuf schemas): `/LIDAR_TOP`, `/CAM_*/image_rect_compressed`, `/CAM_*/camera_info`,
//! `/tf` with the ego pose at every sensor stamp and the extrinsics re-published at every
//! keyframe, plus `/CAM_*/superpixels` class maps and an unrelated JSON `/odom` channel.

use crate::out::McapOut;
use crate::truth::{CameraTruth, FramesTruth, PoseTruth, SweepTruth};
use crate::{Dialect, GeneratedDrive, Simulation, WrittenDrive, encode_jpeg};
use anyhow::Context as _;
use foxglove::Encode;
use foxglove::messages::{
    CameraCalibration, CompressedImage, FrameTransform, PackedElementField, PointCloud, Quaternion,
    RawImage, Timestamp, Vector3, packed_element_field::NumericType,
};
use nalgebra::Isometry3;
use prost::Message as _;
use std::collections::BTreeMap;
use superflow_schemas::Stamp;

/// Frame of the ego vehicle.
pub const EGO_FRAME: &str = "base_link";
/// The world frame.
pub const MAP_FRAME: &str = "map";
/// Frame and topic of the LiDAR.
pub const LIDAR: &str = "LIDAR_TOP";
/// Sweeps with index divisible by this are keyframes (2 Hz).
const KEYFRAME_EVERY: usize = 10;

fn timestamp(stamp: Stamp) -> anyhow::Result<Timestamp> {
    let (sec, nanosec) = stamp.to_sec_nanosec();
    Timestamp::new_checked(u32::try_from(sec)?, nanosec).context("timestamp out of range")
}

fn frame_transform(
    stamp: Stamp,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> anyhow::Result<Vec<u8>> {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation.quaternion();
    Ok(FrameTransform {
        timestamp: Some(timestamp(stamp)?),
        parent_frame_id: parent.to_string(),
        child_frame_id: child.to_string(),
        translation: Some(Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        }),
        rotation: Some(Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }),
    }
    .encode_to_vec())
}

fn schema<T: Encode>() -> anyhow::Result<(String, String, Vec<u8>)> {
    let schema = T::get_schema().context("foxglove type without schema")?;
    Ok((schema.name, schema.encoding, schema.data.into_owned()))
}

/// Writes the drive; returns the MCAP bytes and the ground truth.
pub fn write(sim: &Simulation) -> anyhow::Result<GeneratedDrive> {
    let mut out = McapOut::default();
    out.set_chunk_size(sim.options.chunk_size);
    let none = BTreeMap::new;
    let (pc_name, pc_enc, pc_data) = schema::<PointCloud>()?;
    let (ci_name, ci_enc, ci_data) = schema::<CompressedImage>()?;
    let (cc_name, cc_enc, cc_data) = schema::<CameraCalibration>()?;
    let (ri_name, ri_enc, ri_data) = schema::<RawImage>()?;
    let (ft_name, ft_enc, ft_data) = schema::<FrameTransform>()?;

    let lidar_channel = out.channel(
        &format!("/{LIDAR}"),
        "lidar",
        (&pc_name, &pc_enc, &pc_data),
        "protobuf",
        none(),
    );
    let tf_channel = out.channel(
        "/tf",
        "transforms",
        (&ft_name, &ft_enc, &ft_data),
        "protobuf",
        none(),
    );
    let camera_channels: Vec<(usize, usize, usize)> = sim
        .rig
        .cameras
        .iter()
        .map(|cam| {
            (
                out.channel(
                    &format!("/{}/image_rect_compressed", cam.name),
                    "image",
                    (&ci_name, &ci_enc, &ci_data),
                    "protobuf",
                    none(),
                ),
                out.channel(
                    &format!("/{}/camera_info", cam.name),
                    "calibration",
                    (&cc_name, &cc_enc, &cc_data),
                    "protobuf",
                    none(),
                ),
                out.channel(
                    &format!("/{}/superpixels", cam.name),
                    "superpixels",
                    (&ri_name, &ri_enc, &ri_data),
                    "protobuf",
                    none(),
                ),
            )
        })
        .collect();
    let odom_schema = br#"{"type":"object","properties":{"timestamp":{"type":"object"},"pos":{"type":"array"},"orientation":{"type":"array"},"vel":{"type":"array"}}}"#;
    let odom_channel = out.channel(
        "/odom",
        "other",
        ("Pose", "jsonschema", odom_schema),
        "json",
        none(),
    );

    // LiDAR: motion compensated into the LiDAR frame at the end of the sweep.
    let fields: Vec<PackedElementField> = ["x", "y", "z", "intensity", "ring"]
        .iter()
        .enumerate()
        .map(|(i, name)| PackedElementField {
            name: (*name).to_string(),
            offset: 4 * i as u32,
            r#type: NumericType::Float32 as i32,
        })
        .collect();
    let mut sweeps = Vec::new();
    let mut lidar_stamps = Vec::new();
    for (k, returns) in sim.sweeps.iter().enumerate() {
        let (_, end) = sim.timing.sweep_span(k);
        let lidar_from_map = (sim.map_from_ego(end) * sim.rig.ego_from_lidar).inverse();
        let mut data = Vec::with_capacity(returns.len() * 20);
        for r in returns {
            let p = lidar_from_map * r.point_in_map;
            for v in [
                p.x as f32,
                p.y as f32,
                p.z as f32,
                r.intensity,
                f32::from(r.ring),
            ] {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        let msg = PointCloud {
            timestamp: Some(timestamp(end)?),
            frame_id: LIDAR.to_string(),
            pose: None,
            point_stride: 20,
            fields: fields.clone(),
            data: data.into(),
        };
        out.message(lidar_channel, end.nanos(), end.nanos(), msg.encode_to_vec());
        out.message(
            tf_channel,
            end.nanos(),
            end.nanos(),
            frame_transform(end, MAP_FRAME, EGO_FRAME, &sim.map_from_ego(end))?,
        );
        if k % KEYFRAME_EVERY == 0 {
            out.message(
                tf_channel,
                end.nanos(),
                end.nanos(),
                frame_transform(end, EGO_FRAME, LIDAR, &sim.rig.ego_from_lidar)?,
            );
        }
        sweeps.push(SweepTruth {
            stamp_nanos: end.nanos(),
            points: returns.len() as u64,
        });
        lidar_stamps.push(end);
    }
    let keyframe_stamps: Vec<Stamp> = lidar_stamps
        .iter()
        .step_by(KEYFRAME_EVERY)
        .copied()
        .collect();

    // Cameras: keyframe images are logged at the keyframe LiDAR stamp, as the converter does.
    let mut cameras = Vec::new();
    for (i, cam) in sim.rig.cameras.iter().enumerate() {
        let (image_channel, info_channel, superpixel_channel) = camera_channels[i];
        let stamps = &sim.camera_stamps[i];
        let mut keyframe_log = BTreeMap::new();
        for key in &keyframe_stamps {
            if let Some(nearest) = stamps.iter().min_by_key(|s| s.nanos_since(*key).abs()) {
                keyframe_log.insert(*nearest, *key);
            }
        }
        let calibration = &cam.calibration;
        let k: Vec<f64> = calibration.k.transpose().iter().copied().collect(); // row-major
        let mut p = Vec::with_capacity(12);
        for row in 0..3 {
            p.extend_from_slice(&k[row * 3..row * 3 + 3]);
            p.push(0.0);
        }
        for (frame, stamp) in sim.frames[i].iter().zip(stamps) {
            let log_time = keyframe_log.get(stamp).unwrap_or(stamp).nanos();
            let jpeg = encode_jpeg(&frame.image)?;
            out.message(
                image_channel,
                log_time,
                log_time,
                CompressedImage {
                    timestamp: Some(timestamp(*stamp)?),
                    frame_id: cam.name.to_string(),
                    data: jpeg.into(),
                    format: "jpeg".into(),
                }
                .encode_to_vec(),
            );
            out.message(
                info_channel,
                log_time,
                log_time,
                CameraCalibration {
                    timestamp: Some(timestamp(*stamp)?),
                    frame_id: cam.name.to_string(),
                    width: calibration.width,
                    height: calibration.height,
                    distortion_model: String::new(),
                    d: Vec::new(),
                    k: k.clone(),
                    r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    p: p.clone(),
                }
                .encode_to_vec(),
            );
            out.message(
                superpixel_channel,
                log_time,
                log_time,
                RawImage {
                    timestamp: Some(timestamp(*stamp)?),
                    frame_id: cam.name.to_string(),
                    width: frame.classes.width,
                    height: frame.classes.height,
                    encoding: "mono8".into(),
                    step: frame.classes.width,
                    data: frame.classes.data.clone().into(),
                }
                .encode_to_vec(),
            );
            out.message(
                tf_channel,
                stamp.nanos(),
                stamp.nanos(),
                frame_transform(*stamp, MAP_FRAME, EGO_FRAME, &sim.map_from_ego(*stamp))?,
            );
            if keyframe_log.contains_key(stamp) {
                out.message(
                    tf_channel,
                    log_time,
                    log_time,
                    frame_transform(*stamp, EGO_FRAME, cam.name, &cam.ego_from_optical())?,
                );
            }
        }
        cameras.push(CameraTruth {
            name: cam.name.to_string(),
            image_topic: format!("/{}/image_rect_compressed", cam.name),
            calibration_topic: format!("/{}/camera_info", cam.name),
            superpixel_topic: format!("/{}/superpixels", cam.name),
            frame_id: cam.name.to_string(),
            width: calibration.width,
            height: calibration.height,
            k: k.clone()
                .try_into()
                .map_err(|_| anyhow::anyhow!("K is 3x3"))?,
            distortion_model: String::new(),
            d: Vec::new(),
            ego_from_camera: PoseTruth::from(&cam.ego_from_optical()),
            stamps_nanos: stamps.iter().map(|s| s.nanos()).collect(),
        });
    }

    // CAN-bus style odometry at 10 Hz: JSON, not used by superflow.
    let end = sim.timing.start.add_nanos(sim.timing.duration_nanos);
    let mut stamp = sim.timing.start;
    while stamp < end {
        let pose = sim.map_from_ego(stamp);
        let (sec, nsec) = stamp.to_sec_nanosec();
        let q = pose.rotation.quaternion();
        let t = pose.translation.vector;
        let json = format!(
            r#"{{"timestamp":{{"sec":{sec},"nsec":{nsec}}},"pos":[{},{},{}],"orientation":[{},{},{},{}],"vel":[{},0.0,0.0]}}"#,
            t.x,
            t.y,
            t.z,
            q.w,
            q.i,
            q.j,
            q.k,
            crate::sim::EGO_SPEED
        );
        out.message(
            odom_channel,
            stamp.nanos(),
            stamp.nanos(),
            json.into_bytes(),
        );
        stamp = stamp.add_nanos(100_000_000);
    }

    let description = format!(
        "superflow synthetic street, {} s, {} cameras, 16-beam LiDAR",
        sim.options.duration_secs(),
        sim.rig.cameras.len()
    );
    out.metadata(
        "scene-info",
        &[
            ("description", &description),
            ("name", "street_foxglove"),
            ("location", "procedural"),
            ("vehicle", "superflow-sim"),
            ("date_captured", "2023-11-14"),
        ],
    );

    let (mcap, channels) = out.finish("", Some(mcap::Compression::Lz4))?;
    let truth = sim.ground_truth(WrittenDrive {
        dialect: Dialect::Foxglove,
        profile: "",
        compression: "lz4",
        frames: FramesTruth {
            map: MAP_FRAME.into(),
            ego: EGO_FRAME.into(),
            lidar: LIDAR.into(),
        },
        lidar_topic: format!("/{LIDAR}"),
        motion_compensated: true,
        stamp_at: "sweep_end",
        channels,
        sweeps,
        lidar_stamps,
        cameras,
    });
    Ok(GeneratedDrive { mcap, truth })
}
