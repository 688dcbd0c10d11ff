//! Code shared by the GPU kernels (compiled to SPIR-V by rust-gpu) and the host.
//!
//! Everything here is `no_std`, allocation-free and deterministic, so the very same
//! functions run inside a compute shader and inside a CPU reference on the host.
//! Parameter structs are `#[repr(C)]`; on the host they are also `bytemuck::Pod` so
//! they can be pushed as push constants byte for byte.
#![no_std]
#![forbid(unsafe_code)]

// The SH loops write `each_index!(16, ..)` for the 16 coefficients of degree 3.
const _: () = assert!(splat::layout::MAX_SH_COEFFS == 16);

/// Runs `$body` for `$i` = 0..N, each a constant (N one of 2, 3, 4, 6, 8, 9, 10, 11, 12,
/// 15, 16, 24, 32): no loop. llvmpipe does not unroll rust-gpu's loops, and a loop's
/// counter indexing a local array is a dynamic index, which it turns into code that
/// tries every element; constant indices cost nothing. Not everywhere: written out this
/// way, the deformation's 24-joint loops come out wrong on llvmpipe 22.3 (posed means
/// off by 1e19 against the CPU reference, `deform_gpu_matches_cpu_reference`), so they
/// stay loops.
///
/// N may also be a const generic parameter of the enclosing function (an identifier,
/// `each_index!(W, j => ..)`) whose value is 4, 8, 16 or 32: the body is then written
/// once per count, and code is generated only for the count an instance of the function
/// has (rustc drops the arms of a `match` on a constant after monomorphization; no
/// branch reaches the SPIR-V). Inside, an index of an array of `W` elements is two
/// constants, so no bounds check reaches the SPIR-V either: the kernels' generic tiles
/// (`nn_lavapipe`) come out as if each width were unrolled by hand.
#[macro_export]
macro_rules! each_index {
    ($n:ident, $i:ident => $body:block) => {{
        const { assert!(matches!($n, 4 | 8 | 16 | 32), "each_index!: a const generic count must be 4, 8, 16 or 32") };
        match $n {
            4 => $crate::each_index!(4, $i => $body),
            8 => $crate::each_index!(8, $i => $body),
            16 => $crate::each_index!(16, $i => $body),
            32 => $crate::each_index!(32, $i => $body),
            _ => unreachable!(),
        }
    }};
    (2, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body }
    }};
    (3, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body }
    }};
    (4, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
    }};
    (6, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body }
    }};
    (8, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
    }};
    (9, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body }
    }};
    (10, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body }
    }};
    (11, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body } { let $i: usize = 10; $body }
    }};
    (12, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body } { let $i: usize = 10; $body } { let $i: usize = 11; $body }
    }};
    (15, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body } { let $i: usize = 10; $body } { let $i: usize = 11; $body }
        { let $i: usize = 12; $body } { let $i: usize = 13; $body } { let $i: usize = 14; $body }
    }};
    (16, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body } { let $i: usize = 10; $body } { let $i: usize = 11; $body }
        { let $i: usize = 12; $body } { let $i: usize = 13; $body } { let $i: usize = 14; $body } { let $i: usize = 15; $body }
    }};
    (24, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body } { let $i: usize = 10; $body } { let $i: usize = 11; $body }
        { let $i: usize = 12; $body } { let $i: usize = 13; $body } { let $i: usize = 14; $body } { let $i: usize = 15; $body }
        { let $i: usize = 16; $body } { let $i: usize = 17; $body } { let $i: usize = 18; $body } { let $i: usize = 19; $body }
        { let $i: usize = 20; $body } { let $i: usize = 21; $body } { let $i: usize = 22; $body } { let $i: usize = 23; $body }
    }};
    (32, $i:ident => $body:block) => {{
        { let $i: usize = 0; $body } { let $i: usize = 1; $body } { let $i: usize = 2; $body } { let $i: usize = 3; $body }
        { let $i: usize = 4; $body } { let $i: usize = 5; $body } { let $i: usize = 6; $body } { let $i: usize = 7; $body }
        { let $i: usize = 8; $body } { let $i: usize = 9; $body } { let $i: usize = 10; $body } { let $i: usize = 11; $body }
        { let $i: usize = 12; $body } { let $i: usize = 13; $body } { let $i: usize = 14; $body } { let $i: usize = 15; $body }
        { let $i: usize = 16; $body } { let $i: usize = 17; $body } { let $i: usize = 18; $body } { let $i: usize = 19; $body }
        { let $i: usize = 20; $body } { let $i: usize = 21; $body } { let $i: usize = 22; $body } { let $i: usize = 23; $body }
        { let $i: usize = 24; $body } { let $i: usize = 25; $body } { let $i: usize = 26; $body } { let $i: usize = 27; $body }
        { let $i: usize = 28; $body } { let $i: usize = 29; $body } { let $i: usize = 30; $body } { let $i: usize = 31; $body }
    }};
}

pub mod adam;
pub mod chunks;
pub mod cloth_loss;
pub mod deform;
pub mod fixed_point;
pub mod half;
pub mod lpips;
pub mod nn;
pub mod radix_sort;
pub mod real;
pub mod scan;
pub mod skinning;
#[cfg(not(target_arch = "spirv"))]
pub mod spirv_module;
pub mod splat;
pub mod ssim;
pub mod triplane;
