//! The pieces a training step needs to be one submission: Adam guarded on the GPU
//! (`train::adam_step_guarded`), a render's overflow raising that guard
//! (`train::flag_exceeds`), and a backward recorded after its forward in the same
//! recording (`SplatRenderer::recorded_forward`).

use drape_engine::ops::adam::{AdamGroup, LrSchedule};
use drape_engine::ops::splat::render::{Accumulation, GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::BufferDesc;
use drape_tests::gpu;
use drape_tests::splat::{camera, scene};

/// With the guard down a guarded step is the plain step, bit for bit, and counts once
/// `advance` is called; with it raised nothing moves: parameters, moments, step count.
#[test]
fn a_guarded_adam_step_is_the_plain_step_or_nothing() {
    let gpu = gpu();
    let len = 1000;
    let params: Vec<f32> = (0..len).map(|i| (i as f32 * 0.37).sin()).collect();
    let grads: Vec<f32> = (0..len).map(|i| (i as f32 * 0.11).cos() * 0.1).collect();
    let g = gpu.upload("grads", &grads).expect("upload");
    let run = |guard_value: Option<u32>| {
        let mut p = gpu.upload("params", &params).expect("upload");
        let group =
            AdamGroup::new(&gpu, "guarded", len, LrSchedule::constant(0.01)).expect("group");
        let mut guard = gpu
            .create_buffer("guard", BufferDesc::readback(4))
            .expect("guard");
        gpu.write_buffer(&mut guard, &[guard_value.unwrap_or(0)])
            .expect("write");
        let mut rec = gpu.record("adam").expect("record");
        match guard_value {
            Some(_) => group
                .record_guarded_step(&mut rec, &p, &g, &guard)
                .expect("record step"),
            None => group.record_step(&mut rec, &p, &g).expect("record step"),
        }
        rec.submit_and_wait().expect("submit");
        let out = gpu.read_buffer::<f32>(&mut p, len).expect("read");
        (out, group)
    };
    let (plain, plain_group) = run(None);
    let (down, down_group) = run(Some(0));
    let differ = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .filter(|(x, y)| x.to_bits() != y.to_bits())
            .count()
    };
    assert_eq!(
        differ(&down, &plain),
        0,
        "guard down: parameters that differ from the plain step's"
    );
    assert_eq!(down_group.steps(), 0, "the step count waits for the host");
    down_group.advance();
    assert_eq!(down_group.steps(), plain_group.steps());
    let (raised, mut raised_group) = run(Some(3));
    assert_eq!(
        differ(&raised, &params),
        0,
        "guard raised: parameters that moved"
    );
    let (m, v) = raised_group.read_moments(&gpu).expect("moments");
    assert!(
        m.iter().chain(&v).all(|&x| x == 0.0),
        "guard raised: the moments stayed zero"
    );
    assert_eq!(raised_group.steps(), 0);
}

/// A frame recorded with too small an intersection capacity raises the guard in the
/// same recording; with room it does not. The backward recorded after the forward in
/// one recording (no finish between them) gives the gradients of the forward and
/// backward submitted apart.
#[test]
fn an_overflowed_render_raises_the_guard_and_a_backward_can_share_its_recording() {
    let gpu = gpu();
    let cloud = scene(600, 1, 7);
    let cam = camera(64, 48);
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(&gpu, "guard scene", &cloud).expect("upload");
    let mut renderer =
        SplatRenderer::new(&gpu, cam.width, cam.height, cloud.len()).expect("renderer");
    let mut guard = gpu
        .create_buffer("guard", BufferDesc::readback(4))
        .expect("guard");
    let ones = gpu
        .upload(
            "grad rgb",
            &vec![1.0f32; 3 * (cam.width * cam.height) as usize],
        )
        .expect("upload");
    let zeros = gpu
        .upload("zeros", &vec![0.0f32; (cam.width * cam.height) as usize])
        .expect("upload");
    let together = GaussianBuffers::new(&gpu, "grads together", cloud.len(), 1).expect("grads");
    let apart = GaussianBuffers::new(&gpu, "grads apart", cloud.len(), 1).expect("grads");
    // Deterministic accumulation: the two orders of recording give the same bits.
    let accumulation = Accumulation::Deterministic;

    renderer.set_intersection_capacity(1).expect("capacity");
    let mut frame = |renderer: &mut SplatRenderer, with_backward: bool| {
        renderer
            .prepare_forward(&gaussians, &cam, &settings)
            .expect("prepare");
        renderer
            .prepare_backward(accumulation)
            .expect("prepare backward");
        let mut rec = gpu.record("frame").expect("record");
        rec.fill(&guard, 0);
        renderer
            .record_forward(&mut rec, &gaussians)
            .expect("forward");
        renderer
            .record_overflow_flag(&mut rec, &guard)
            .expect("flag");
        if with_backward {
            let saved = renderer.recorded_forward();
            renderer
                .record_backward(
                    &mut rec,
                    &saved,
                    &gaussians,
                    &ones,
                    &zeros,
                    &zeros,
                    &together,
                    accumulation,
                )
                .expect("backward");
        }
        rec.submit_and_wait().expect("submit");
        let flag = gpu.read_buffer::<u32>(&mut guard, 1).expect("read")[0];
        (renderer.finish_forward().expect("finish").rerendered, flag)
    };
    assert_eq!(
        frame(&mut renderer, true),
        (true, 1),
        "capacity 1: overflowed, and the guard says so on the GPU"
    );
    assert_eq!(
        frame(&mut renderer, true),
        (false, 0),
        "grown: no overflow, guard down"
    );

    let saved = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward")
        .saved;
    renderer
        .backward(
            &saved,
            &gaussians,
            &ones,
            &zeros,
            &zeros,
            &apart,
            accumulation,
        )
        .expect("backward");
    let mut together = together;
    let mut apart = apart;
    let n = cloud.len();
    for (name, a, b) in [
        ("means", &mut together.means, &mut apart.means),
        (
            "opacity",
            &mut together.opacity_logits,
            &mut apart.opacity_logits,
        ),
    ] {
        let per = if name == "means" { 3 } else { 1 };
        let a = gpu.read_buffer::<f32>(a, per * n).expect("read");
        let b = gpu.read_buffer::<f32>(b, per * n).expect("read");
        assert!(
            a.iter().any(|&x| x != 0.0),
            "{name}: the check would be vacuous (all zero)"
        );
        let differ = a
            .iter()
            .zip(&b)
            .filter(|(x, y)| x.to_bits() != y.to_bits())
            .count();
        assert_eq!(differ, 0, "{name}: values that differ between the backward recorded with its forward and the one submitted apart");
    }
}
