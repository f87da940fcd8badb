//! The SuperFlow losses against an independent PyTorch implementation of the same
//! formulas (`trainer/reference/make_loss_fixture.py` → `tests/fixtures/losses.json`, and
//! `--mixed` → `losses_mixed.json`, a batch of two rigs with three cameras and one):
//! values and gradients with respect to the 3D and 2D features, both `L_d2s` forms.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use burn::tensor::{Device, Int, Tensor, TensorData};
use serde_json::Value;
use superflow_trainer::loss::{D2sForm, LossConfig, LossInputs, LossPlan, SuperFlowLoss};

fn fixture(name: &str) -> Value {
    let path = format!("{}/tests/fixtures/{name}", env!("CARGO_MANIFEST_DIR"));
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// `sample_cameras` of a fixture: `config.cameras` is one count for every sample, or the
/// count of each.
fn sample_cameras(config: &Value) -> Vec<u32> {
    let batch = config["batch"].as_u64().unwrap() as usize;
    let counts: Vec<u32> = match &config["cameras"] {
        Value::Array(per_sample) => per_sample
            .iter()
            .map(|k| k.as_u64().unwrap() as u32)
            .collect(),
        k => vec![k.as_u64().unwrap() as u32; batch],
    };
    assert_eq!(counts.len(), batch);
    std::iter::once(0)
        .chain(counts.iter().scan(0, |sum, k| {
            *sum += k;
            Some(*sum)
        }))
        .collect()
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn ints<T: TryFrom<u64>>(v: &Value) -> Vec<T>
where
    T::Error: std::fmt::Debug,
{
    let flat: Vec<u64> = match v.as_array().unwrap().first() {
        Some(Value::Array(_)) => v
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_u64().unwrap()))
            .collect(),
        _ => v
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap())
            .collect(),
    };
    flat.into_iter().map(|x| T::try_from(x).unwrap()).collect()
}

/// max |a − b| / max |b|.
fn rel_err(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0_f64, |m, v| m.max(v.abs())).max(1e-30);
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - y).abs())
        .fold(0.0, f64::max)
        / scale
}

fn scalar(t: &Tensor<1>) -> f64 {
    f64::from(t.clone().into_data().try_into_vec::<f32>().unwrap()[0])
}

#[test]
fn losses_and_gradients_match_the_pytorch_reference() {
    matches_the_reference("losses.json");
}

/// Two rigs in one batch: each sample pools over its own cameras only.
#[test]
fn losses_of_a_mixed_rig_batch_match_the_pytorch_reference() {
    matches_the_reference("losses_mixed.json");
}

fn matches_the_reference(name: &str) {
    let fx = fixture(name);
    let c = &fx["config"];
    let get = |k: &str| c[k].as_u64().unwrap() as usize;
    let (b, f, h, w, d) = (
        get("batch"),
        get("frames"),
        get("height"),
        get("width"),
        get("dim"),
    );
    let sample_cameras = sample_cameras(c);
    let images = f * sample_cameras[b] as usize;
    let num_superpixels: Vec<u32> = ints(&fx["num_superpixels"]);
    let superpixels: Vec<u16> = ints(&fx["superpixels"]);
    let pairing_point: Vec<u32> = ints(&fx["pairing_point"]);
    let pairing_superpixel: Vec<u32> = ints(&fx["pairing_superpixel"]);
    let pairing_clouds: Vec<u32> = ints(&fx["pairing_clouds"]);
    let n = fx["num_points"].as_u64().unwrap() as usize;
    let expected = &fx["expected"];

    let device = Device::flex().autodiff();
    let plan = LossPlan::new(
        &LossInputs {
            batch: b,
            frames: f,
            sample_cameras: &sample_cameras,
            key_frame: get("key_frame"),
            height: h,
            width: w,
            num_superpixels: &num_superpixels,
            superpixels: &superpixels,
            pairing_point: &pairing_point,
            pairing_superpixel: &pairing_superpixel,
            pairing_clouds: &pairing_clouds,
        },
        1,
        &device,
    )
    .unwrap();
    let slots = &expected["slots"];
    let sc_slots: Vec<usize> = plan.sc.iter().map(|m| m.len).collect();
    let tc_slots: Vec<usize> = plan.tc.iter().map(|m| m.len).collect();
    assert_eq!(sc_slots, ints::<usize>(&slots["sc"]));
    assert_eq!(tc_slots, ints::<usize>(&slots["tc"]));
    assert_eq!(plan.d2s.len as u64, slots["d2s"].as_u64().unwrap());
    assert_eq!(plan.sampled_pixels(), images * h * w);

    for form in [D2sForm::Infonce, D2sForm::Cosine] {
        let config = LossConfig {
            temperature: c["temperature"].as_f64().unwrap(),
            w_sc: c["weights"]["sc"].as_f64().unwrap(),
            w_tc: c["weights"]["tc"].as_f64().unwrap(),
            w_d2s: c["weights"]["d2s"].as_f64().unwrap(),
            d2s: form,
            pixel_stride: 1,
        };
        let points = Tensor::<2>::from_data(
            TensorData::new(floats(&fx["point_features"]), [n, d]),
            &device,
        )
        .require_grad();
        let pixels = Tensor::<4>::from_data(
            TensorData::new(floats(&fx["pixel_features"]), [images, d, h, w]),
            &device,
        )
        .require_grad();
        // Pixel rows in the plan's order.
        let order: Vec<i64> = plan
            .pixels
            .iter()
            .map(|&[i, r, col]| ((i as usize * h + r as usize) * w + col as usize) as i64)
            .collect();
        let order = Tensor::<1, Int>::from_data(TensorData::new(order, [images * h * w]), &device);
        let pixel_rows = pixels
            .clone()
            .permute([0, 2, 3, 1])
            .reshape([images * h * w, d])
            .select(0, order);
        let pairing_rows = points.clone().select(0, plan.pairing_point.clone());
        let loss = SuperFlowLoss::new(config);
        let terms = loss.forward(pairing_rows, pixel_rows, &plan);

        let close = |name: &str, got: f64, want: f64| {
            let rel = (got - want).abs() / want.abs().max(1e-12);
            assert!(
                rel <= 1e-5,
                "{name} ({form:?}): {got} vs {want} (rel {rel:.2e})"
            );
        };
        for (i, want) in f64s(&expected["l_sc_frames"]).into_iter().enumerate() {
            close(
                &format!("L_sc frame {i}"),
                scalar(&terms.sc_frames[i]),
                want,
            );
        }
        close(
            "L_sc",
            scalar(&terms.sc),
            expected["l_sc"].as_f64().unwrap(),
        );
        close(
            "L_tc",
            scalar(&terms.tc),
            expected["l_tc"].as_f64().unwrap(),
        );
        let (d2s_key, total_key, suffix) = match form {
            D2sForm::Infonce => ("l_d2s_infonce", "total_infonce", "infonce"),
            D2sForm::Cosine => ("l_d2s_cosine", "total_cosine", "cosine"),
        };
        close(
            "L_d2s",
            scalar(&terms.d2s),
            expected[d2s_key].as_f64().unwrap(),
        );
        close(
            "total",
            scalar(&terms.total),
            expected[total_key].as_f64().unwrap(),
        );

        let grads = terms.total.backward();
        let gp = points
            .grad(&grads)
            .unwrap()
            .into_data()
            .try_into_vec::<f32>()
            .unwrap();
        let gx = pixels
            .grad(&grads)
            .unwrap()
            .into_data()
            .try_into_vec::<f32>()
            .unwrap();
        let ep = f64s(&expected[format!("grad_point_features_{suffix}").as_str()]);
        let ex = f64s(&expected[format!("grad_pixel_features_{suffix}").as_str()]);
        let (rp, rx) = (rel_err(&gp, &ep), rel_err(&gx, &ex));
        assert!(
            rp <= 1e-5,
            "∂total/∂point features ({form:?}): rel err {rp:.2e}"
        );
        assert!(
            rx <= 1e-5,
            "∂total/∂pixel features ({form:?}): rel err {rx:.2e}"
        );
        eprintln!(
            "{form:?}: total {:.6} (reference {:.6}); gradient rel. errors {rp:.1e} (3D), {rx:.1e} (2D)",
            scalar(&terms.total),
            expected[total_key].as_f64().unwrap()
        );
    }
}

/// An id beyond its frame's superpixel count is an error naming the section, not a
/// panic or an out-of-bounds scatter.
#[test]
fn a_superpixel_id_beyond_the_count_is_an_error() {
    let fx = fixture("losses.json");
    let num_superpixels: Vec<u32> = ints(&fx["num_superpixels"]);
    let superpixels: Vec<u16> = ints(&fx["superpixels"]);
    let pairing_point: Vec<u32> = ints(&fx["pairing_point"]);
    let mut pairing_superpixel: Vec<u32> = ints(&fx["pairing_superpixel"]);
    let pairing_clouds: Vec<u32> = ints(&fx["pairing_clouds"]);
    pairing_superpixel[3] = 99;
    let err = LossPlan::new(
        &LossInputs {
            batch: 2,
            frames: 3,
            sample_cameras: &[0, 2, 4],
            key_frame: 1,
            height: 6,
            width: 8,
            num_superpixels: &num_superpixels,
            superpixels: &superpixels,
            pairing_point: &pairing_point,
            pairing_superpixel: &pairing_superpixel,
            pairing_clouds: &pairing_clouds,
        },
        1,
        &Device::flex(),
    )
    .unwrap_err();
    assert_eq!(err.section, "pairing_superpixel", "{err}");
    assert!(err.to_string().contains("id 99"), "{err}");
}
