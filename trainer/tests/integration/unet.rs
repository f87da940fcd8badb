//! The sparse convolutions equal burn's dense 3D convolutions on a small voxel grid —
//! outputs at the active sites and gradients with respect to features and weights —
//! with kernel maps built by the pipeline's own code (`superflow_pipeline::sample::kernel_maps`).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use burn::module::Param;
use burn::tensor::module::{conv_transpose3d, conv3d};
use burn::tensor::ops::{ConvOptions, ConvTransposeOptions};
use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor, TensorData};
use superflow_pipeline::sample::kernel_maps::{downsample, neighbour_map};
use superflow_trainer::init::InitRng;
use superflow_trainer::unet::{KERNEL_2, KERNEL_3, LevelMaps, SparseConv};

const G: usize = 6; // grid side
const CIN: usize = 3;
const COUT: usize = 4;

/// Active cells of a 6³ grid (about 40 %), deterministic.
fn active_cells() -> Vec<[i32; 3]> {
    let mut rng = InitRng::new(7, "cells");
    let mut cells = Vec::new();
    for x in 0..G as i32 {
        for y in 0..G as i32 {
            for z in 0..G as i32 {
                if rng.normal() > 0.25 {
                    cells.push([x, y, z]);
                }
            }
        }
    }
    cells
}

fn flat(cells: &[[i32; 3]], side: usize) -> Vec<i64> {
    cells
        .iter()
        .map(|c| ((c[0] as usize * side + c[1] as usize) * side + c[2] as usize) as i64)
        .collect()
}

fn index(values: Vec<i64>, device: &Device) -> Tensor<1, Int> {
    let n = values.len();
    Tensor::from_data(TensorData::new(values, [n]), device)
}

fn random(shape: [usize; 2], name: &str, device: &Device) -> Tensor<2> {
    let v = InitRng::new(3, name).normals(shape[0] * shape[1], 1.0);
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// Sparse rows `[n, c]` placed into a dense `[1, c, side, side, side]` grid.
fn densify(rows: Tensor<2>, cells: &[[i32; 3]], side: usize, device: &Device) -> Tensor<5> {
    let [_, c] = rows.dims();
    Tensor::zeros([side * side * side, c], device)
        .select_assign(
            0,
            index(flat(cells, side), device),
            rows,
            IndexingUpdateOp::Add,
        )
        .transpose()
        .reshape([1, c, side, side, side])
}

/// Dense `[1, c, side³]` output read at `cells` → `[n, c]`.
fn sparsify(dense: Tensor<5>, cells: &[[i32; 3]], side: usize, device: &Device) -> Tensor<2> {
    let [_, c, ..] = dense.dims();
    dense
        .reshape([c, side * side * side])
        .transpose()
        .select(0, index(flat(cells, side), device))
}

fn values(t: Tensor<2>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().unwrap()
}

fn assert_close(what: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len(), "{what}");
    let scale = b.iter().fold(0.0_f32, |m, v| m.max(v.abs())).max(1e-6);
    let err = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(
        err <= 1e-5 * scale.max(1.0),
        "{what}: max |diff| {err} (scale {scale})"
    );
}

/// Sparse weight `[k, cin, cout]` → dense `[cout, cin, s, s, s]` (conv) or
/// `[cin, cout, s, s, s]` (transposed conv); offsets enumerate x slowest, z fastest.
fn dense_weight(w: Tensor<3>, side: usize, transposed: bool) -> Tensor<5> {
    let [_, cin, cout] = w.dims();
    let w = w.reshape([side, side, side, cin, cout]);
    if transposed {
        w.permute([3, 4, 0, 1, 2])
    } else {
        w.permute([4, 3, 0, 1, 2])
    }
}

/// Runs `sparse` and `dense` on the same leaves, compares outputs and the gradients of
/// a random linear functional of the outputs.
fn compare(
    what: &str,
    features: Tensor<2>,
    weight: Tensor<3>,
    sparse: impl Fn(Tensor<2>, &SparseConv) -> Tensor<2>,
    dense: impl Fn(Tensor<2>, Tensor<3>) -> Tensor<2>,
) {
    let device = features.device();
    let x = features.require_grad();
    let conv = SparseConv {
        weight: Param::from_tensor(weight),
    };
    let w = conv.weight.val();
    let out_sparse = sparse(x.clone(), &conv);
    let out_dense = dense(x.clone(), w.clone());
    assert_eq!(out_sparse.dims(), out_dense.dims(), "{what}: output rows");
    assert_close(
        &format!("{what}: outputs"),
        &values(out_sparse.clone()),
        &values(out_dense.clone()),
    );
    let probe = random(out_sparse.dims(), "probe", &device);
    let gs = (out_sparse * probe.clone()).sum().backward();
    let gd = (out_dense * probe).sum().backward();
    let grad = |t: &Tensor<2>, g| values(t.grad(g).unwrap());
    assert_close(
        &format!("{what}: ∂/∂features"),
        &grad(&x, &gs),
        &grad(&x, &gd),
    );
    let wgrad = |g| {
        w.grad(g)
            .unwrap()
            .into_data()
            .try_into_vec::<f32>()
            .unwrap()
    };
    assert_close(&format!("{what}: ∂/∂weights"), &wgrad(&gs), &wgrad(&gd));
}

fn level(cells: &[[i32; 3]], device: &Device) -> (LevelMaps, Vec<[i32; 3]>) {
    let nbr = neighbour_map(cells);
    let (parents, down) = downsample(cells);
    let flat_pairs = |m: &superflow_pipeline::sample::kernel_maps::KernelMap| {
        m.pairs.iter().flatten().copied().collect::<Vec<u32>>()
    };
    let (np, dp) = (flat_pairs(&nbr), flat_pairs(&down));
    let maps = LevelMaps::from_host(
        cells.len(),
        &np,
        &nbr.starts,
        Some((&dp, &down.starts)),
        device,
    );
    (maps, parents)
}

#[test]
fn submanifold_conv_equals_dense_conv3d_at_active_sites() {
    let device = Device::flex().autodiff();
    let cells = active_cells();
    let (maps, _) = level(&cells, &device);
    let features = random([cells.len(), CIN], "features", &device);
    let weight = SparseConv::new(KERNEL_3, CIN, COUT, 1, "w", &device)
        .weight
        .val();
    compare(
        "3×3×3",
        features,
        weight,
        |x, conv| conv.forward(x, &maps),
        |x, w| {
            let dense = conv3d(
                densify(x, &cells, G, &device),
                dense_weight(w, 3, false),
                None,
                ConvOptions::new([1, 1, 1], [1, 1, 1], [1, 1, 1], 1),
            );
            sparsify(dense, &cells, G, &device)
        },
    );
}

#[test]
fn strided_conv_and_its_transpose_equal_dense_ones() {
    let device = Device::flex().autodiff();
    let cells = active_cells();
    let (maps, parents) = level(&cells, &device);
    let half = G / 2;
    let weight = SparseConv::new(KERNEL_2, CIN, COUT, 2, "down", &device)
        .weight
        .val();
    compare(
        "down 2×2×2 stride 2",
        random([cells.len(), CIN], "features", &device),
        weight,
        |x, conv| conv.forward_down(x, &maps, parents.len()),
        |x, w| {
            let dense = conv3d(
                densify(x, &cells, G, &device),
                dense_weight(w, 2, false),
                None,
                ConvOptions::new([2, 2, 2], [0, 0, 0], [1, 1, 1], 1),
            );
            sparsify(dense, &parents, half, &device)
        },
    );
    let weight = SparseConv::new(KERNEL_2, CIN, COUT, 3, "up", &device)
        .weight
        .val();
    compare(
        "up (transposed) 2×2×2 stride 2",
        random([parents.len(), CIN], "coarse", &device),
        weight,
        |x, conv| conv.forward_up(x, &maps),
        |x, w| {
            let dense = conv_transpose3d(
                densify(x, &parents, half, &device),
                dense_weight(w, 2, true),
                None,
                ConvTransposeOptions::new([2, 2, 2], [0, 0, 0], [0, 0, 0], [1, 1, 1], 1),
            );
            sparsify(dense, &cells, G, &device)
        },
    );
}
