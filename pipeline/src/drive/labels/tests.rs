//! Tests of the `[labels]` settings and the raw id → class map.

use super::*;
use std::collections::BTreeMap;

#[test]
fn a_mapping_maps_and_sends_unlisted_ids_to_ignore_index() {
    let config = LabelConfig {
        mapping: BTreeMap::from([
            ("1".to_string(), 0),
            ("0x11".to_string(), 1),
            ("9".to_string(), 255),
        ]),
        classes: vec!["barrier".into(), "vegetation".into()],
        ..LabelConfig::default()
    };
    let map = config.label_map().unwrap();
    assert!(map.has_mapping());
    assert_eq!(
        map.classes_of(&[1, 17, 9, 2, 1000]),
        Ok(vec![0, 1, 255, 255, 255])
    );
    let config = LabelConfig {
        ignore_index: 0,
        ..config
    };
    let e = config.label_map().unwrap_err();
    assert_eq!(e.setting, "labels.ignore_index");
}

#[test]
fn without_a_mapping_raw_ids_are_classes_below_the_named_ones() {
    let map = LabelConfig {
        classes: (0..17).map(|c| format!("class {c}")).collect(),
        ..LabelConfig::default()
    }
    .label_map()
    .unwrap();
    assert_eq!(map.classes_of(&[0, 16, 3]), Ok(vec![0, 16, 3]));
    assert_eq!(map.classes_of(&[0, 17, 3]), Err(17));
    assert!(map.limit().contains("17 classes"), "{}", map.limit());
    let unnamed = LabelConfig::default().label_map().unwrap();
    assert_eq!(unnamed.classes_of(&[255, 31]), Ok(vec![255, 31]));
    assert_eq!(unnamed.class_of(256), Err(256));
}

#[test]
fn bad_settings_name_the_setting() {
    let bad = |config: LabelConfig| config.validate().unwrap_err().setting;
    let mapping = |key: &str, class: u8| LabelConfig {
        mapping: BTreeMap::from([(key.to_string(), class)]),
        classes: vec!["a".into(), "b".into()],
        ..LabelConfig::default()
    };
    assert_eq!(bad(mapping("car", 0)), "labels.mapping.car");
    assert_eq!(bad(mapping("3", 2)), "labels.mapping.3");
    assert!(mapping("3", 255).validate().is_ok());
    assert_eq!(
        bad(LabelConfig {
            label_mask: Some(0),
            ..LabelConfig::default()
        }),
        "labels.label_mask"
    );
    assert_eq!(
        bad(LabelConfig {
            field: Some(String::new()),
            ..LabelConfig::default()
        }),
        "labels.field"
    );
}
