//! `superflow-pipeline inspect --json` on the sample drives: the stable report agrees
//! with each drive's ground truth.

use serde_json::Value;
use superflow_pipeline::inspect::{INSPECT_FORMAT, InspectReport};

use super::root;

fn inspect(args: &[&str]) -> (bool, String, String) {
    super::pipeline("inspect", args)
}

#[test]
fn json_report_matches_the_ground_truth() {
    for drive in ["street_foxglove", "street_ros2"] {
        let mcap = format!("recordings/drives/{drive}.mcap");
        let (ok, stdout, stderr) = inspect(&["--json", "--mcap", &mcap]);
        assert!(ok, "{stderr}");
        let full: InspectReport = serde_json::from_str(&stdout).unwrap();
        assert_eq!(full.format, INSPECT_FORMAT);
        assert_eq!(full.drives.len(), 1);
        let report = &full.drives[0];
        let truth: Value = serde_json::from_slice(
            &std::fs::read(root().join(format!("recordings/drives/{drive}.truth.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(
            report.dialect,
            if drive.ends_with("ros2") {
                "ros2"
            } else {
                "foxglove_protobuf"
            }
        );
        // The drive and, when its labels are in a sidecar, `<drive>.labels.mcap`.
        let labels = &truth["labels"];
        let sidecar_channels = labels["sidecar"]["channels"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        assert_eq!(
            report.files.len(),
            1 + usize::from(!labels["sidecar"].is_null())
        );
        assert!(report.files.iter().all(|f| f.damage.is_empty()));
        assert_eq!(report.problems, None);
        assert_eq!(report.skipped.total(), 0);

        // Every channel of the truth (the drive's and its sidecar's), with its count and
        // role.
        let channels: Vec<&Value> = truth["channels"]
            .as_array()
            .unwrap()
            .iter()
            .chain(&sidecar_channels)
            .collect();
        for channel in &channels {
            let topic = channel["topic"].as_str().unwrap();
            let found = report
                .channels
                .iter()
                .find(|c| c.topic == topic)
                .expect(topic);
            assert_eq!(
                found.message_count,
                channel["message_count"].as_u64().unwrap(),
                "{topic}"
            );
            assert_eq!(found.schema, channel["schema_name"].as_str().unwrap());
            let role = channel["role"].as_str().unwrap();
            let expected_role = if role == "other" { "ignored" } else { role };
            assert_eq!(found.role.name(), expected_role, "{topic}");
        }
        assert_eq!(report.channels.len(), channels.len());

        // The labels: where they are, every sweep labelled, the points of each class.
        let found = report
            .labels
            .as_ref()
            .expect("the sample drives are labelled");
        let form = serde_json::to_value(found.form.as_ref().unwrap()).unwrap();
        assert_eq!(form["form"], labels["form"]);
        match labels["form"].as_str().unwrap() {
            "field" => assert_eq!(form["field"], labels["field"]),
            _ => {
                assert_eq!(form["topic"], labels["topic"]);
                let file = form["file"].as_str().unwrap();
                let want = labels["sidecar"]["file"].as_str().unwrap();
                assert!(file.ends_with(&format!("/{want}")), "{file}");
            }
        }
        let sweeps = truth["lidar"]["sweeps"].as_array().unwrap().len();
        assert_eq!((found.sweeps, found.sweeps_labelled), (sweeps, sweeps));
        assert_eq!((found.errors, &found.first_error), (0, &None));
        let per_class: Vec<u64> = labels["points_per_class"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n.as_u64().unwrap())
            .collect();
        for (id, points) in per_class.iter().enumerate() {
            assert_eq!(
                found.raw_ids.get(&(id as u32)).copied().unwrap_or(0),
                *points,
                "class {id}"
            );
        }
        assert_eq!(
            found.raw_ids.values().sum::<u64>(),
            per_class.iter().sum::<u64>()
        );

        let lidar = &truth["lidar"];
        assert_eq!(report.lidar_topic.as_deref(), lidar["topic"].as_str());
        assert_eq!(report.lidar_frame.as_deref(), lidar["frame_id"].as_str());
        assert_eq!(
            report.lidar_sweeps,
            lidar["sweeps"].as_array().unwrap().len()
        );
        let lidar_rate = report
            .channels
            .iter()
            .find(|c| Some(c.topic.as_str()) == lidar["topic"].as_str())
            .unwrap()
            .rate_hz
            .unwrap();
        assert!((lidar_rate - 20.0).abs() < 1e-6, "{lidar_rate}");

        let cameras = truth["cameras"].as_array().unwrap();
        assert_eq!(report.cameras.len(), cameras.len());
        for camera in cameras {
            let found = report
                .cameras
                .iter()
                .find(|c| c.image_topic == camera["image_topic"].as_str().unwrap())
                .unwrap();
            assert_eq!(found.frame_id, camera["frame_id"].as_str().unwrap());
            assert_eq!(
                found.calibration_topic.as_deref(),
                camera["calibration_topic"].as_str()
            );
            assert_eq!(
                found.superpixel_topic.as_deref(),
                camera["superpixel_topic"].as_str()
            );
            assert_eq!(found.width, camera["width"].as_u64().map(|w| w as u32));
            assert_eq!(found.height, camera["height"].as_u64().map(|h| h as u32));
            let model = camera["distortion_model"].as_str().unwrap();
            assert_eq!(
                found.distortion_model.as_deref(),
                Some(if model.is_empty() { "none" } else { model })
            );
            assert_eq!(
                found.images,
                camera["stamps_nanos"].as_array().unwrap().len()
            );
            assert!((found.rate_hz.unwrap() - 12.0).abs() < 0.01);
        }

        let sweeps = lidar["sweeps"].as_array().unwrap();
        assert_eq!(
            report.start_stamp_nanos,
            sweeps.first().unwrap()["stamp_nanos"].as_i64()
        );
        assert_eq!(
            report.end_stamp_nanos,
            sweeps.last().unwrap()["stamp_nanos"].as_i64()
        );
        assert_eq!(report.map_frame.as_deref(), truth["frames"]["map"].as_str());
        assert_eq!(report.ego_frame.as_deref(), truth["frames"]["ego"].as_str());
        // Keyframes every 0.5 s over 3 s, each with all six cameras within half a period.
        assert_eq!(report.usable_keyframes, 6);
        // The frame tree reaches every sensor frame from the map.
        let children: Vec<&str> = report.frame_tree.iter().map(|e| e.child.as_str()).collect();
        assert!(children.contains(&lidar["frame_id"].as_str().unwrap()));
        for camera in cameras {
            assert!(children.contains(&camera["frame_id"].as_str().unwrap()));
        }
        assert!(
            report
                .frame_tree
                .iter()
                .filter(|e| e.kind == "static")
                .count()
                >= 7
        );
    }
}

#[test]
fn text_report_and_errors_for_people() {
    let (ok, stdout, _) = inspect(&["--mcap", "recordings/drives"]);
    assert!(ok);
    assert!(
        stdout.contains("== drive 1 of 2") && stdout.contains("== drive 2 of 2"),
        "{stdout}"
    );
    assert!(
        stdout.contains("dialect foxglove_protobuf") && stdout.contains("dialect ros2"),
        "{stdout}"
    );
    assert!(stdout.contains("/LIDAR_TOP") && stdout.contains("/lidar_top/points_raw"));
    assert!(
        stdout.contains("labels: field `label` of the LiDAR clouds; 60 of 60 sweeps labelled")
            && stdout.contains("street_ros2.labels.mcap: /lidar_top/points_raw/labels; 60 of 60"),
        "{stdout}"
    );
    let (ok, _, stderr) = inspect(&["--mcap", "recordings/drives/nope.mcap"]);
    assert!(!ok);
    assert!(stderr.contains("recordings/drives/nope.mcap"), "{stderr}");
}
