//! The recorder binds buffers by the kernel parameter's name, checks each binding's
//! access against the SPIR-V's `NonWritable` declarations, and places barriers from
//! those declared accesses: one only where a command reads or writes what an earlier
//! one wrote since the last barrier, or writes what one read. Synchronization
//! validation is on in every test context, so a derived barrier that is missing shows
//! up as a validation message (and fails the test that caused it).

use drape_engine::kernels::{check_module, Kernel};
use drape_engine::{Buffer, EngineError, PassBuilder, PassTimings};
use drape_shared::adam::LossParams;
use drape_tests::gpu;

const LEN: u32 = 1000;

fn params() -> LossParams {
    LossParams { len: LEN, scale: 1.0, _pad: [0; 2] }
}

fn groups() -> [u32; 3] {
    [LEN.div_ceil(256), 1, 1]
}

/// The error a pass of `train::add_into` (bindings `src` read-only, `dst` writable)
/// gives when bound by `bind`.
fn binding_error(bind: impl for<'r, 'a> FnOnce(PassBuilder<'r, 'a>, &'a Buffer, &'a Buffer) -> PassBuilder<'r, 'a>) -> EngineError {
    let gpu = gpu();
    let a = gpu.upload("a", &[1.0f32; LEN as usize]).expect("upload");
    let b = gpu.upload("b", &[2.0f32; LEN as usize]).expect("upload");
    let mut rec = gpu.record("binding errors").expect("record");
    let pass = rec.pass("test.add", Kernel::TrainAddInto);
    let err = bind(pass, &a, &b).push(&params()).dispatch(groups()).expect_err("a wrong binding must be refused");
    assert_eq!(rec.barrier_count(), 0);
    err
}

fn assert_binding_error(err: &EngineError, binding: &str, words: &[&str]) {
    let text = err.to_string();
    match err {
        EngineError::Binding { kernel, binding: b, pass, .. } => {
            assert_eq!(*kernel, "train::add_into", "{text}");
            assert_eq!(b, binding, "{text}");
            assert_eq!(pass, "test.add", "{text}");
        }
        other => panic!("expected a binding error, got {other:?}"),
    }
    for w in words {
        assert!(text.contains(w), "'{w}' missing from: {text}");
    }
}

#[test]
fn a_name_the_kernel_lacks_is_an_error_naming_the_kernel_and_the_binding() {
    let err = binding_error(|p, a, b| p.read("source", a).write("dst", b));
    assert_binding_error(&err, "source", &["train::add_into", "no binding of that name", "src, dst"]);
}

#[test]
fn a_binding_left_unbound_is_an_error() {
    let err = binding_error(|p, a, _| p.read("src", a));
    assert_binding_error(&err, "dst", &["left unbound"]);
}

#[test]
fn writing_through_a_read_only_binding_is_an_error() {
    let err = binding_error(|p, a, b| p.write("src", a).write("dst", b));
    assert_binding_error(&err, "src", &["read-only", "NonWritable", "'a'"]);
}

#[test]
fn reading_through_a_writable_binding_and_binding_twice_are_errors() {
    let err = binding_error(|p, a, b| p.read("src", a).read("dst", b));
    assert_binding_error(&err, "dst", &["writable", "write()"]);
    let err = binding_error(|p, a, b| p.read("src", a).read("src", b).write("dst", b));
    assert_binding_error(&err, "src", &["bound twice"]);
}

/// Commands that share only read-only data get no barrier between them; a read of
/// what was written (RAW), a write of what was read (WAR) and a copy of what was
/// written each get one. The sums prove the order held.
#[test]
fn barriers_are_derived_from_declared_access() {
    let gpu = gpu();
    let n = LEN as usize;
    let x = gpu.upload("x", &vec![1.0f32; n]).expect("upload");
    let mut y = gpu.upload("y", &vec![10.0f32; n]).expect("upload");
    let mut z = gpu.upload("z", &vec![100.0f32; n]).expect("upload");
    let mut w = gpu.upload("w", &vec![1000.0f32; n]).expect("upload");
    let mut copy = gpu.upload("copy", &vec![0.0f32; n]).expect("upload");
    let p = params();
    let mut rec = gpu.record("derived barriers").expect("record");
    // y += x and z += x: both only read x, write different buffers.
    rec.pass("add.y", Kernel::TrainAddInto).read("src", &x).write("dst", &y).push(&p).dispatch(groups()).expect("y");
    rec.pass("add.z", Kernel::TrainAddInto).read("src", &x).write("dst", &z).push(&p).dispatch(groups()).expect("z");
    assert_eq!(rec.barrier_count(), 0, "independent passes must not be ordered");
    // w += y reads what add.y wrote: a barrier.
    rec.pass("add.w", Kernel::TrainAddInto).read("src", &y).write("dst", &w).push(&p).dispatch(groups()).expect("w");
    assert_eq!(rec.barrier_count(), 1, "read after write");
    // y += z writes y, which add.w read since the barrier (and reads z, written before it).
    rec.pass("add.y2", Kernel::TrainAddInto).read("src", &z).write("dst", &y).push(&p).dispatch(groups()).expect("y2");
    assert_eq!(rec.barrier_count(), 2, "write after read");
    // A copy of what add.y2 wrote.
    rec.copy(&y, &copy, u64::from(LEN) * 4);
    assert_eq!(rec.barrier_count(), 3, "copy after write");
    rec.submit_and_wait().expect("submit");
    let read = |b: &mut Buffer| gpu.read_buffer::<f32>(b, n).expect("read");
    // y = 10 + 1 = 11; z = 100 + 1 = 101; w = 1000 + 11 = 1011; y = 11 + 101 = 112.
    assert!(read(&mut z).iter().all(|&v| v == 101.0));
    assert!(read(&mut w).iter().all(|&v| v == 1011.0), "add.w ran before add.y finished");
    assert!(read(&mut y).iter().all(|&v| v == 112.0), "add.y2 ran before add.w read y");
    assert!(read(&mut copy).iter().all(|&v| v == 112.0));
}

/// The start-up check reads each binding's name and access from the module: a
/// renamed parameter or a dropped `NonWritable` is a mismatch naming the binding.
#[test]
fn a_module_whose_bindings_disagree_with_the_manifest_is_named() {
    let original = Kernel::TrainAddInto.spirv();
    check_module(Kernel::TrainAddInto, original).expect("the committed module matches");

    // Rename `src` (an OpName literal "src\0") to `srx`.
    let mut renamed = original.to_vec();
    let at = renamed.windows(4).position(|w| w == b"src\0").expect("OpName of src");
    renamed[at + 2] = b'x';
    let text = check_module(Kernel::TrainAddInto, &renamed).expect_err("renamed").to_string();
    assert!(text.contains("binding 0") && text.contains("'srx'") && text.contains("'src'"), "{text}");

    // Turn the NonWritable decoration (OpDecorate %id 24) into Restrict (19).
    let words: Vec<u32> = original.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    let mut at = 5;
    let mut patched = original.to_vec();
    let mut found = false;
    while at < words.len() {
        let (op, count) = (words[at] & 0xffff, (words[at] >> 16) as usize);
        if op == 71 && count == 3 && words[at + 2] == 24 {
            patched[(at + 2) * 4..(at + 3) * 4].copy_from_slice(&19u32.to_le_bytes());
            found = true;
        }
        at += count;
    }
    assert!(found, "add_into declares src NonWritable");
    let text = check_module(Kernel::TrainAddInto, &patched).expect_err("writable").to_string();
    assert!(text.contains("'src'") && text.contains("writable in the module"), "{text}");
}

/// Passes free to overlap are not counted twice in a submission's GPU time.
#[test]
fn busy_time_counts_overlapping_passes_once() {
    let timings = PassTimings {
        passes: vec![("a".into(), 2.0), ("b".into(), 2.0), ("c".into(), 1.0)],
        // a and b overlap by 1 ms; c starts after a gap.
        intervals: vec![(0.0, 2.0), (1.0, 3.0), (5.0, 6.0)],
    };
    assert_eq!(timings.total_ms(), 5.0);
    assert_eq!(timings.busy_ms(), 4.0);
    let mut two = timings.clone();
    two.extend(timings);
    assert_eq!(two.busy_ms(), 8.0, "a second submission's passes follow the first's");
}
