//! Round trips, hand-computed bytes and hostile payloads of the CDR codec, and the
//! schema texts checked against rosbag2's layout and the Rust types.

use std::collections::BTreeSet;
use std::fmt::Debug;

use byteorder::{BigEndian, LittleEndian};
use serde::de::value::Error as ValueError;
use serde::de::{DeserializeOwned, Visitor};
use serde::{Deserializer, Serialize, forward_to_deserialize_any};

use super::*;

fn header(sec: i32, nanosec: u32, frame_id: &str) -> Header {
    Header {
        stamp: Ros2Time { sec, nanosec },
        frame_id: frame_id.to_owned(),
    }
}

fn sample_point_cloud() -> PointCloud2 {
    let names = ["x", "y", "z", "intensity"];
    let fields = names
        .iter()
        .zip(0u32..)
        .map(|(name, i)| PointField {
            name: (*name).to_owned(),
            offset: 4 * i,
            datatype: PointField::FLOAT32,
            count: 1,
        })
        .collect();
    let points = 5u32;
    let data = (0..points * 16).map(|i| (i * 7 % 251) as u8).collect();
    PointCloud2 {
        header: header(1_700_000_000, 123_456_789, "lidar_top"),
        height: 1,
        width: points,
        fields,
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * points,
        data,
        is_dense: true,
    }
}

fn sample_compressed_image() -> CompressedImage {
    CompressedImage {
        header: header(-3, 999_999_999, "cam_front"),
        format: "jpeg".to_owned(),
        data: vec![0xff, 0xd8, 0xff, 0xe0, 0x00, 0x10, 0xff, 0xd9],
    }
}

fn sample_image() -> Image {
    Image {
        header: header(12, 34, "cam_left"),
        height: 2,
        width: 3,
        encoding: "rgb8".to_owned(),
        is_bigendian: 0,
        step: 9,
        data: (0..18).collect(),
    }
}

fn sample_camera_info() -> CameraInfo {
    CameraInfo {
        header: header(5, 6, "cam_front"),
        height: 900,
        width: 1600,
        distortion_model: "plumb_bob".to_owned(),
        d: vec![-0.1, 0.01, 0.001, -0.002, 0.0],
        k: [1266.4, 0.0, 816.3, 0.0, 1266.4, 491.5, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            1266.4, 0.0, 816.3, 0.0, 0.0, 1266.4, 491.5, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        binning_x: 1,
        binning_y: 2,
        roi: RegionOfInterest {
            x_offset: 10,
            y_offset: 20,
            height: 30,
            width: 40,
            do_rectify: true,
        },
    }
}

fn sample_transform_stamped(child: &str) -> TransformStamped {
    TransformStamped {
        header: header(7, 8, "map"),
        child_frame_id: child.to_owned(),
        transform: Transform {
            translation: Vector3 {
                x: 1.5,
                y: -2.25,
                z: 3.0,
            },
            rotation: Quaternion {
                x: 0.0,
                y: 0.0,
                z: std::f64::consts::FRAC_1_SQRT_2,
                w: std::f64::consts::FRAC_1_SQRT_2,
            },
        },
    }
}

fn sample_tf_message() -> TfMessage {
    TfMessage {
        transforms: vec![
            sample_transform_stamped("base_link"),
            sample_transform_stamped("lidar_top"),
            TransformStamped::default(),
        ],
    }
}

/// Encodes, checks the header, decodes and compares; also checks that the body
/// is consumed to its last byte.
fn round_trip<T>(msg: &T)
where
    T: Serialize + DeserializeOwned + PartialEq + Debug,
{
    let bytes = encode(msg).unwrap();
    assert_eq!(bytes[..4], [0x00, 0x01, 0x00, 0x00]);
    let back: T = decode(&bytes).unwrap();
    assert_eq!(&back, msg);
    let (_, consumed) =
        cdr_encoding::from_bytes::<T, LittleEndian>(&bytes[ENCAPSULATION_HEADER_LEN..]).unwrap();
    assert_eq!(consumed, bytes.len() - ENCAPSULATION_HEADER_LEN);
}

/// A `CDR_BE` payload of `msg`.
fn encode_big_endian<T: Serialize>(msg: &T) -> Vec<u8> {
    let mut bytes = vec![0x00, 0x00, 0x00, 0x00];
    bytes.extend(cdr_encoding::to_vec::<T, BigEndian>(msg).unwrap());
    bytes
}

#[test]
fn round_trips_every_message_type() {
    round_trip(&Ros2Time {
        sec: -1,
        nanosec: 500,
    });
    round_trip(&header(1, 2, ""));
    round_trip(&header(1, 2, "a frame with ünïcödé"));
    round_trip(&PointField {
        name: "rgb".to_owned(),
        offset: 16,
        datatype: PointField::UINT32,
        count: 1,
    });
    round_trip(&sample_point_cloud());
    round_trip(&PointCloud2::default());
    round_trip(&sample_compressed_image());
    round_trip(&sample_image());
    round_trip(&sample_camera_info());
    round_trip(&CameraInfo::default());
    round_trip(&RegionOfInterest::default());
    round_trip(&Vector3 {
        x: f64::MIN_POSITIVE,
        y: f64::MAX,
        z: -0.0,
    });
    round_trip(&Quaternion::default());
    round_trip(&Transform::default());
    round_trip(&sample_transform_stamped("x"));
    round_trip(&sample_tf_message());
    round_trip(&TfMessage::default());
}

#[test]
fn header_encodes_to_hand_computed_bytes() {
    let bytes = encode(&header(1, 2, "map")).unwrap();
    #[rustfmt::skip]
    let expected = [
        0x00, 0x01, 0x00, 0x00, // encapsulation: CDR_LE, no options
        0x01, 0x00, 0x00, 0x00, // stamp.sec = 1
        0x02, 0x00, 0x00, 0x00, // stamp.nanosec = 2
        0x04, 0x00, 0x00, 0x00, // frame_id length, NUL included
        b'm', b'a', b'p', 0x00, // frame_id
    ];
    assert_eq!(bytes, expected);
    assert_eq!(decode::<Header>(&expected).unwrap(), header(1, 2, "map"));
}

#[test]
fn transform_stamped_aligns_f64_to_body_start() {
    let msg = TransformStamped {
        header: header(1, 2, "map"),
        child_frame_id: "base".to_owned(),
        transform: Transform {
            translation: Vector3 {
                x: 1.0,
                y: -2.0,
                z: 0.5,
            },
            rotation: Quaternion::default(),
        },
    };
    #[rustfmt::skip]
    let expected: Vec<u8> = [
        &[0x00, 0x01, 0x00, 0x00][..],          // encapsulation
        &[0x01, 0x00, 0x00, 0x00],              // body 0: stamp.sec
        &[0x02, 0x00, 0x00, 0x00],              // body 4: stamp.nanosec
        &[0x04, 0x00, 0x00, 0x00],              // body 8: frame_id length
        b"map\0",                               // body 12
        &[0x05, 0x00, 0x00, 0x00],              // body 16: child_frame_id length
        b"base\0",                              // body 20..25
        &[0x00; 7],                             // body 25..32: pad to 8 (body-relative)
        &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],        // body 32: translation.x = 1.0
        &[0, 0, 0, 0, 0, 0, 0x00, 0xc0],        // body 40: translation.y = -2.0
        &[0, 0, 0, 0, 0, 0, 0xe0, 0x3f],        // body 48: translation.z = 0.5
        &[0; 8],                                // body 56: rotation.x = 0
        &[0; 8],                                // body 64: rotation.y = 0
        &[0; 8],                                // body 72: rotation.z = 0
        &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],        // body 80: rotation.w = 1.0
    ]
    .concat();
    assert_eq!(expected.len(), 4 + 88);
    assert_eq!(encode(&msg).unwrap(), expected);
    assert_eq!(decode::<TransformStamped>(&expected).unwrap(), msg);
}

#[test]
fn big_endian_payloads_decode_to_the_same_values() {
    #[rustfmt::skip]
    let header_be = [
        0x00, 0x00, 0x00, 0x00, // encapsulation: CDR_BE
        0x00, 0x00, 0x00, 0x01, // stamp.sec = 1
        0x00, 0x00, 0x00, 0x02, // stamp.nanosec = 2
        0x00, 0x00, 0x00, 0x04, // frame_id length
        b'm', b'a', b'p', 0x00,
    ];
    assert_eq!(decode::<Header>(&header_be).unwrap(), header(1, 2, "map"));

    fn same<T: Serialize + DeserializeOwned + PartialEq + Debug>(msg: &T) {
        let be = encode_big_endian(msg);
        assert_ne!(be[ENCAPSULATION_HEADER_LEN..], encode(msg).unwrap()[4..]);
        assert_eq!(&decode::<T>(&be).unwrap(), msg);
    }
    same(&sample_point_cloud());
    same(&sample_compressed_image());
    same(&sample_image());
    same(&sample_camera_info());
    same(&sample_tf_message());
}

#[test]
fn trailing_padding_is_ignored() {
    let mut bytes = encode(&header(1, 2, "map!")).unwrap();
    bytes.extend_from_slice(&[0, 0, 0]);
    assert_eq!(decode::<Header>(&bytes).unwrap(), header(1, 2, "map!"));
}

#[test]
fn short_buffers_and_other_representations_are_rejected() {
    for len in 0..4 {
        let bytes = [0x00, 0x01, 0x00][..len.min(3)].to_vec();
        assert!(matches!(
            decode::<Header>(&bytes),
            Err(CdrError::TooShort { len: l }) if l == bytes.len()
        ));
    }
    let body = &encode(&header(1, 2, "map")).unwrap()[2..];
    for id in [
        [0x00, 0x02],
        [0x00, 0x03],
        [0x00, 0x07],
        [0x01, 0x00],
        [0xff, 0xff],
    ] {
        let bytes = [&id[..], body].concat();
        let err = decode::<Header>(&bytes).unwrap_err();
        assert!(matches!(err, CdrError::UnsupportedRepresentation { id: got } if got == id));
        assert!(err.to_string().contains("representation"), "{err}");
    }
}

#[test]
fn every_truncation_of_a_point_cloud_is_an_error() {
    let bytes = encode(&sample_point_cloud()).unwrap();
    for len in 0..bytes.len() {
        let result = decode::<PointCloud2>(&bytes[..len]);
        assert!(result.is_err(), "truncated to {len} bytes: {result:?}");
    }
    let be = encode_big_endian(&sample_point_cloud());
    for len in 0..be.len() {
        assert!(decode::<PointCloud2>(&be[..len]).is_err());
    }
}

#[test]
fn huge_declared_lengths_are_errors_without_allocation() {
    // A sequence count of u32::MAX right at the start of the body, 16 bytes left.
    let mut tf = vec![0x00, 0x01, 0x00, 0x00, 0xff, 0xff, 0xff, 0xff];
    tf.extend_from_slice(&[0; 12]);
    assert_eq!(tf.len(), 20);
    assert!(matches!(
        decode::<TfMessage>(&tf),
        Err(CdrError::Decode { len: 20, .. })
    ));

    // `data` is the last field of these: patch its (empty) length to u32::MAX.
    fn patch_last_len<T: Serialize + DeserializeOwned + Debug>(msg: &T) {
        let mut bytes = encode(msg).unwrap();
        let at = bytes.len() - 4;
        bytes[at..].copy_from_slice(&[0xff; 4]);
        bytes.extend_from_slice(&[0; 8]);
        assert!(decode::<T>(&bytes).is_err());
    }
    patch_last_len(&CompressedImage::default());
    patch_last_len(&Image::default());

    // Huge string lengths, and huge counts of every sequence in the middle of a message.
    let mut frame = encode(&header(1, 2, "")).unwrap();
    frame[12..16].copy_from_slice(&[0xff; 4]);
    assert!(decode::<Header>(&frame).is_err());
    for msg_bytes in [
        encode(&sample_point_cloud()).unwrap(),
        encode(&sample_camera_info()).unwrap(),
        encode(&sample_tf_message()).unwrap(),
    ] {
        for at in 4..msg_bytes.len().saturating_sub(4) {
            let mut bytes = msg_bytes.clone();
            bytes[at..at + 4].copy_from_slice(&[0xff; 4]);
            let _ = decode::<PointCloud2>(&bytes);
            let _ = decode::<CameraInfo>(&bytes);
            let _ = decode::<TfMessage>(&bytes);
        }
    }
}

/// A deterministic xorshift64* generator for the fuzz-style loops, so they repeat
/// exactly and need no dependency.
#[derive(Debug, Clone)]
struct Rng(u64);

impl Rng {
    /// The next 64 pseudo-random bits.
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// Uniform-ish in `0..n` (`n > 0`).
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    /// An index into a slice of `len > 0` elements.
    fn index(&mut self, len: usize) -> usize {
        self.below(len as u64) as usize
    }
}

fn decode_all(bytes: &[u8]) {
    let _ = decode::<Header>(bytes);
    let _ = decode::<PointCloud2>(bytes);
    let _ = decode::<CompressedImage>(bytes);
    let _ = decode::<Image>(bytes);
    let _ = decode::<CameraInfo>(bytes);
    let _ = decode::<TfMessage>(bytes);
}

#[test]
fn garbage_never_panics() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for _ in 0..3000 {
        let len = rng.index(300);
        let mut bytes: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        if len >= 2 && rng.below(4) != 0 {
            bytes[0] = 0;
            bytes[1] = rng.below(2) as u8;
        }
        decode_all(&bytes);
    }
    // Valid messages with a few bytes flipped reach deeper into the decoders.
    let valid = [
        encode(&sample_point_cloud()).unwrap(),
        encode(&sample_compressed_image()).unwrap(),
        encode(&sample_image()).unwrap(),
        encode(&sample_camera_info()).unwrap(),
        encode(&sample_tf_message()).unwrap(),
    ];
    for _ in 0..3000 {
        let mut bytes = valid[rng.index(valid.len())].clone();
        for _ in 0..1 + rng.below(3) {
            let at = 4 + rng.index(bytes.len() - 4);
            bytes[at] = rng.next() as u8;
        }
        decode_all(&bytes);
    }
    assert!(decode::<Header>(&[0x00, 0x01, 0x00, 0x00, 0x01]).is_err());
    // Invalid UTF-8 and invalid bools are errors.
    let mut bad_utf8 = encode(&header(0, 0, "ab")).unwrap();
    bad_utf8[16] = 0xff;
    assert!(decode::<Header>(&bad_utf8).is_err());
    let mut bad_bool = encode(&RegionOfInterest::default()).unwrap();
    let last = bad_bool.len() - 1;
    bad_bool[last] = 2;
    assert!(decode::<RegionOfInterest>(&bad_bool).is_err());
}

#[test]
fn megabyte_data_fields_are_one_octet_block() {
    let image = Image {
        header: header(1, 2, "cam"),
        height: 1024,
        width: 4096,
        encoding: "mono8".to_owned(),
        is_bigendian: 0,
        step: 4096,
        data: (0..4096 * 1024).map(|i: u32| (i % 253) as u8).collect(),
    };
    let bytes = encode(&image).unwrap();
    // 4 (encapsulation) + 8 (stamp) + 8 ("cam") + 8 (height, width) + 10 ("mono8")
    // + 1 (is_bigendian) + 1 (pad) + 4 (step) + 4 (count): then the pixels, verbatim.
    assert_eq!(bytes.len(), 48 + image.data.len());
    assert_eq!(bytes[48..], image.data[..]);
    let back: Image = decode(&bytes).unwrap();
    assert_eq!(back, image);
}

#[test]
fn ros2_time_converts_to_and_from_nanoseconds() {
    let t = Ros2Time {
        sec: -2,
        nanosec: 300_000_000,
    };
    assert_eq!(t.as_nanos(), -1_700_000_000);
    assert_eq!(Ros2Time::from_nanos(-1_700_000_000), Some(t));
    assert_eq!(Ros2Time::from_nanos(i64::MAX), None);
    assert_eq!(PointField::datatype_size(PointField::FLOAT64), Some(8));
    assert_eq!(PointField::datatype_size(0), None);
}

// ----- schema texts -----

const SEPARATOR: &str =
    "================================================================================";

/// Probes the field names serde derives for `T`.
struct FieldNames<'a>(&'a mut &'static [&'static str]);

impl<'de> Deserializer<'de> for FieldNames<'_> {
    type Error = ValueError;

    fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, ValueError> {
        Err(serde::de::Error::custom("not a struct"))
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _: &'static str,
        fields: &'static [&'static str],
        _: V,
    ) -> Result<V::Value, ValueError> {
        *self.0 = fields;
        Err(serde::de::Error::custom("probed"))
    }

    forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes
        byte_buf option unit unit_struct newtype_struct seq tuple tuple_struct map enum
        identifier ignored_any
    }
}

fn field_names<T: DeserializeOwned>() -> Vec<&'static str> {
    let mut fields: &'static [&'static str] = &[];
    let _ = T::deserialize(FieldNames(&mut fields));
    fields.to_vec()
}

/// The field lines of a `.msg` text as (type, name); constants left out.
fn msg_fields(text: &str) -> Vec<(&str, &str)> {
    text.lines()
        .map(|line| line.split('#').next().unwrap_or("").trim())
        .filter(|line| !line.is_empty() && !line.contains('='))
        .map(|line| {
            let mut words = line.split_whitespace();
            (words.next().unwrap(), words.next().unwrap())
        })
        .collect()
}

/// The dependencies of a `.msg` text, named the way rosbag2 names them, sorted.
fn msg_dependencies(text: &str, package: &str) -> BTreeSet<String> {
    const PRIMITIVES: [&str; 14] = [
        "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
        "uint32", "int64", "uint64", "string",
    ];
    msg_fields(text)
        .into_iter()
        .map(|(ty, _)| ty.split('[').next().unwrap())
        .filter(|ty| !PRIMITIVES.contains(ty))
        .map(|ty| {
            if ty.contains('/') {
                ty.to_owned()
            } else {
                format!("{package}/{ty}")
            }
        })
        .collect()
}

/// The `.msg` text of a type, by its rosbag2 dependency name.
fn msg_text(name: &str) -> &'static str {
    match name {
        "builtin_interfaces/Time" => time_msg!(),
        "std_msgs/Header" => header_msg!(),
        "sensor_msgs/PointField" => point_field_msg!(),
        "sensor_msgs/PointCloud2" => point_cloud2_msg!(),
        "sensor_msgs/CompressedImage" => compressed_image_msg!(),
        "sensor_msgs/Image" => image_msg!(),
        "sensor_msgs/RegionOfInterest" => region_of_interest_msg!(),
        "sensor_msgs/CameraInfo" => camera_info_msg!(),
        "geometry_msgs/Vector3" => vector3_msg!(),
        "geometry_msgs/Quaternion" => quaternion_msg!(),
        "geometry_msgs/Transform" => transform_msg!(),
        "geometry_msgs/TransformStamped" => transform_stamped_msg!(),
        "tf2_msgs/TFMessage" => tf_message_msg!(),
        other => panic!("no text for {other}"),
    }
}

/// The serde field names of the Rust mirror of a type.
fn rust_fields(name: &str) -> Vec<&'static str> {
    match name {
        "builtin_interfaces/Time" => field_names::<Ros2Time>(),
        "std_msgs/Header" => field_names::<Header>(),
        "sensor_msgs/PointField" => field_names::<PointField>(),
        "sensor_msgs/PointCloud2" => field_names::<PointCloud2>(),
        "sensor_msgs/CompressedImage" => field_names::<CompressedImage>(),
        "sensor_msgs/Image" => field_names::<Image>(),
        "sensor_msgs/RegionOfInterest" => field_names::<RegionOfInterest>(),
        "sensor_msgs/CameraInfo" => field_names::<CameraInfo>(),
        "geometry_msgs/Vector3" => field_names::<Vector3>(),
        "geometry_msgs/Quaternion" => field_names::<Quaternion>(),
        "geometry_msgs/Transform" => field_names::<Transform>(),
        "geometry_msgs/TransformStamped" => field_names::<TransformStamped>(),
        "tf2_msgs/TFMessage" => field_names::<TfMessage>(),
        other => panic!("no Rust type for {other}"),
    }
}

/// Rebuilds the full text the way rosbag2's `get_full_text` does.
fn rosbag2_full_text(root: &str) -> String {
    fn append(name: &str, seen: &mut BTreeSet<String>) -> String {
        let text = msg_text(name);
        let package = name.split('/').next().unwrap();
        let mut out = text.to_owned();
        for dep in msg_dependencies(text, package) {
            if seen.insert(dep.clone()) {
                out.push('\n');
                out.push_str(SEPARATOR);
                out.push_str("\nMSG: ");
                out.push_str(&dep);
                out.push('\n');
                out.push_str(&append(&dep, seen));
            }
        }
        out
    }
    append(root, &mut BTreeSet::new())
}

const ALL: [(&str, &str, &str); 5] = [
    (
        POINT_CLOUD2,
        "sensor_msgs/PointCloud2",
        POINT_CLOUD2_DEFINITION,
    ),
    (
        COMPRESSED_IMAGE,
        "sensor_msgs/CompressedImage",
        COMPRESSED_IMAGE_DEFINITION,
    ),
    (IMAGE, "sensor_msgs/Image", IMAGE_DEFINITION),
    (
        CAMERA_INFO,
        "sensor_msgs/CameraInfo",
        CAMERA_INFO_DEFINITION,
    ),
    (TF_MESSAGE, "tf2_msgs/TFMessage", TF_MESSAGE_DEFINITION),
];

#[test]
fn schema_texts_have_rosbag2_layout() {
    assert_eq!(SCHEMA_ENCODING, "ros2msg");
    assert_eq!(MESSAGE_ENCODING, "cdr");
    assert_eq!(SEPARATOR.len(), 80);
    for (schema_name, short_name, definition) in ALL {
        assert_eq!(schema_name.replace("/msg/", "/"), short_name);
        assert!(!definition.starts_with('='), "{schema_name}");
        assert!(definition.ends_with('\n'), "{schema_name}");
        assert!(definition.contains(&format!("\n\n{SEPARATOR}\nMSG: std_msgs/Header\n")));
        assert!(definition.contains(&format!("\n{SEPARATOR}\nMSG: builtin_interfaces/Time\n")));
        // Every separator line is exactly 80 '=' and is followed by a MSG: line.
        let lines: Vec<&str> = definition.lines().collect();
        for (i, line) in lines.iter().enumerate() {
            if line.starts_with('=') {
                assert_eq!(*line, SEPARATOR, "{schema_name}");
                assert!(lines[i + 1].starts_with("MSG: "), "{schema_name}");
            }
        }
        assert_eq!(rosbag2_full_text(short_name), definition, "{schema_name}");
    }
    assert!(POINT_CLOUD2_DEFINITION.contains("\nMSG: sensor_msgs/PointField\n"));
    assert!(POINT_CLOUD2_DEFINITION.contains("\nuint8 FLOAT64 = 8\n"));
    assert!(CAMERA_INFO_DEFINITION.contains("\nMSG: sensor_msgs/RegionOfInterest\n"));
    assert!(TF_MESSAGE_DEFINITION.contains("\nMSG: geometry_msgs/TransformStamped\n"));
    assert!(TF_MESSAGE_DEFINITION.contains("\nMSG: geometry_msgs/Quaternion\n"));
    assert_eq!(
        <PointCloud2 as Ros2Message>::SCHEMA_DEFINITION,
        POINT_CLOUD2_DEFINITION
    );
    assert_eq!(<TfMessage as Ros2Message>::SCHEMA_NAME, TF_MESSAGE);
}

#[test]
fn schema_fields_match_the_rust_types() {
    for (schema_name, short_name, definition) in ALL {
        let separator = format!("{SEPARATOR}\n");
        let mut sections = definition.split(&separator);
        let mut named = vec![(short_name.to_owned(), sections.next().unwrap())];
        for section in sections {
            let (first, text) = section.split_once('\n').unwrap();
            named.push((first.strip_prefix("MSG: ").unwrap().to_owned(), text));
        }
        for (name, text) in named {
            let from_text: Vec<&str> = msg_fields(text)
                .into_iter()
                .map(|(_, field)| field)
                .collect();
            assert_eq!(from_text, rust_fields(&name), "{schema_name}: {name}");
        }
    }
    let constants: Vec<&str> = point_field_msg!()
        .lines()
        .filter(|line| line.contains('='))
        .collect();
    assert_eq!(constants.len(), 8);
    for (line, value) in constants.iter().zip(1u8..) {
        assert!(line.ends_with(&format!("= {value}")), "{line}");
    }
}
