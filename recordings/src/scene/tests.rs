//! Tests of the scene: the street's layout and the exact ray casts.

use super::*;
use nalgebra::{Point3, Vector3};

#[test]
fn a_longer_drive_gets_a_longer_street_and_a_short_one_the_same() {
    let street = Scene::street(7);
    assert_eq!(Scene::street_for(7, 12.0).boxes, street.boxes);
    let long = Scene::street_for(7, STREET_TRAVEL_M + 200.0);
    let reach = |scene: &Scene, prefix: &str| {
        scene
            .boxes
            .iter()
            .filter(|b| b.name.starts_with(prefix))
            .map(|b| b.center.x)
            .fold(f64::MIN, f64::max)
    };
    for row in ["building_left", "tree_right", "parked_car"] {
        assert!(reach(&long, row) > reach(&street, row) + 180.0, "{row}");
    }
}

#[test]
fn rays_hit_ground_boxes_and_sky() {
    let scene = Scene::street(7);
    let origin = Point3::new(0.0, 0.0, 1.8);
    let down = scene
        .cast(&origin, &Vector3::new(0.0, 0.0, -1.0), 0.0, 100.0)
        .unwrap();
    assert!((down.distance - 1.8).abs() < 1e-12);
    assert_eq!(down.class, class::DRIVEABLE_SURFACE);
    assert!(scene.cast(&origin, &Vector3::z(), 0.0, 100.0).is_none());
    // From the sidewalk, looking left at a building's middle hits its facade.
    let building = scene
        .boxes
        .iter()
        .find(|b| b.name.starts_with("building_left"))
        .unwrap();
    let from = Point3::new(building.center.x, 12.5, building.center.z);
    let hit = scene.cast(&from, &Vector3::y(), 0.0, 100.0).unwrap();
    assert_eq!(hit.class, class::MANMADE);
    assert!(hit.point.y > 12.5 && hit.point.y < building.center.y);
    assert!((hit.normal.norm() - 1.0).abs() < 1e-12);
    assert!(
        hit.normal.y < -0.99,
        "facade faces the street: {}",
        hit.normal
    );
}

#[test]
fn box_hit_lies_on_the_box_surface() {
    let b = SceneBox {
        name: "b".into(),
        center: Point3::new(10.0, 0.0, 1.0),
        half: Vector3::new(1.0, 2.0, 1.0),
        yaw: 0.3,
        class: class::CAR,
        color: [1.0; 3],
        reflectivity: 1.0,
        motion: None,
    };
    let scene = Scene { boxes: vec![b] };
    let origin = Point3::new(0.0, 0.0, 1.0);
    let hit = scene
        .cast(&origin, &Vector3::new(1.0, 0.0, 0.0), 0.0, 100.0)
        .unwrap();
    // The near face is at local x = -1: point minus centre, rotated back, has x = -1.
    let rel = hit.point - Point3::new(10.0, 0.0, 1.0);
    let (s, c) = 0.3f64.sin_cos();
    assert!(((c * rel.x + s * rel.y) + 1.0).abs() < 1e-9);
    assert!((hit.normal - Vector3::new(-c, -s, 0.0)).norm() < 1e-12);
}
