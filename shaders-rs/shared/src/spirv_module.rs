//! Facts read straight from a SPIR-V module's words: its one entry point's name, its
//! workgroup size and the bindings it declares. The shader builder writes them into the
//! manifest; the engine checks each embedded module against the manifest at start-up.
//! Host-only (never compiled into a kernel).

/// What a compute module declares.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModuleFacts {
    /// Word index where the entry point's name (a nul-terminated literal) starts.
    name_at: usize,
    /// Number of `OpEntryPoint` instructions (a drape module has exactly one).
    pub entry_points: u32,
    /// `LocalSize` execution mode, if declared.
    pub workgroup_size: Option<[u32; 3]>,
    /// Bit `b` set when some variable is decorated `Binding b` (b < 64).
    pub binding_mask: u64,
    /// Bit `b` set when the variable of binding `b` is decorated `NonWritable`: the
    /// kernel only reads it (rust-gpu declares a `&[T]` storage buffer so).
    pub read_only_mask: u64,
    /// Bit `b` set when the variable of binding `b` is a uniform texel buffer (an
    /// `OpTypeImage` of `Dim Buffer`, sampled, in `UniformConstant`): read-only by nature,
    /// bound through a buffer view (`Image!(buffer, type=f32, sampled)` in rust-gpu).
    pub texel_mask: u64,
    /// Bit `b` set when that texel buffer's image declares the format `Rgba32f`
    /// (`Image!(buffer, format=rgba32f, sampled)`): bound through a 4-float view, a
    /// fetch returning 4 consecutive floats; the others declare no format and are
    /// bound through an `R32_SFLOAT` view.
    pub texel4_mask: u64,
}

/// Why a byte string is not a module we can read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SpirvError {
    /// Fewer than 5 header words, or not a whole number of words.
    Length,
    /// The first word is not the SPIR-V magic number.
    Magic,
    /// An instruction's word count is 0 or runs past the end.
    Malformed { word: usize },
    /// A binding number of 64 or more.
    BindingOutOfRange { binding: u32 },
}

impl core::fmt::Display for SpirvError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Length => write!(
                f,
                "not a SPIR-V module: its length is not 5 or more whole words"
            ),
            Self::Magic => write!(f, "not a SPIR-V module: wrong magic number"),
            Self::Malformed { word } => write!(f, "malformed SPIR-V instruction at word {word}"),
            Self::BindingOutOfRange { binding } => {
                write!(f, "binding {binding} is out of range (at most 63)")
            }
        }
    }
}

const MAGIC: u32 = 0x0723_0203;
const OP_ENTRY_POINT: u32 = 15;
const OP_EXECUTION_MODE: u32 = 16;
const OP_NAME: u32 = 5;
const OP_DECORATE: u32 = 71;
const DECORATION_NON_WRITABLE: u32 = 24;
const MODE_LOCAL_SIZE: u32 = 17;
const DECORATION_BINDING: u32 = 33;
const OP_TYPE_IMAGE: u32 = 25;
const OP_TYPE_POINTER: u32 = 32;
const OP_VARIABLE: u32 = 59;
const DIM_BUFFER: u32 = 5;
/// `ImageFormat Rgba32f`.
const FORMAT_RGBA32F: u32 = 1;
const STORAGE_UNIFORM_CONSTANT: u32 = 0;

/// Word `i` of a little-endian byte string.
fn word(bytes: &[u8], i: usize) -> u32 {
    let b = &bytes[i * 4..i * 4 + 4];
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// Reads the facts of a module given as little-endian bytes (as committed on disk).
pub fn inspect(bytes: &[u8]) -> Result<ModuleFacts, SpirvError> {
    if bytes.len() % 4 != 0 || bytes.len() < 20 {
        return Err(SpirvError::Length);
    }
    if word(bytes, 0) != MAGIC {
        return Err(SpirvError::Magic);
    }
    let len = bytes.len() / 4;
    let mut facts = ModuleFacts {
        name_at: 0,
        entry_points: 0,
        workgroup_size: None,
        binding_mask: 0,
        read_only_mask: 0,
        texel_mask: 0,
        texel4_mask: 0,
    };
    // Types precede the variables that use them, and decorations precede both, so one
    // pass collects buffer images, pointers to them and the variables of those pointers.
    let mut buffer_images: [u32; 8] = [0; 8];
    let mut rgba32f: [bool; 8] = [false; 8];
    let mut buffer_image_pointers: [u32; 8] = [0; 8];
    let mut pointer_rgba32f: [bool; 8] = [false; 8];
    let (mut images, mut pointers) = (0usize, 0usize);
    let mut at = 5;
    while at < len {
        let head = word(bytes, at);
        let count = (head >> 16) as usize;
        if count == 0 || at + count > len {
            return Err(SpirvError::Malformed { word: at });
        }
        let operand = |k: usize| word(bytes, at + 1 + k);
        let operands = count - 1;
        match head & 0xffff {
            OP_ENTRY_POINT if operands >= 3 => {
                facts.entry_points += 1;
                facts.name_at = at + 3;
            }
            OP_EXECUTION_MODE if operands >= 5 && operand(1) == MODE_LOCAL_SIZE => {
                facts.workgroup_size = Some([operand(2), operand(3), operand(4)]);
            }
            OP_DECORATE if operands >= 3 && operand(1) == DECORATION_BINDING => {
                let binding = operand(2);
                if binding >= 64 {
                    return Err(SpirvError::BindingOutOfRange { binding });
                }
                facts.binding_mask |= 1 << binding;
            }
            // OpTypeImage: result, sampled type, Dim, Depth, Arrayed, MS, Sampled (1: with a sampler).
            // The eighth operand is the image format.
            OP_TYPE_IMAGE
                if operands >= 7
                    && operand(2) == DIM_BUFFER
                    && operand(6) == 1
                    && images < buffer_images.len() =>
            {
                buffer_images[images] = operand(0);
                rgba32f[images] = operands >= 8 && operand(7) == FORMAT_RGBA32F;
                images += 1;
            }
            OP_TYPE_POINTER
                if operands >= 3
                    && operand(1) == STORAGE_UNIFORM_CONSTANT
                    && buffer_images[..images].contains(&operand(2))
                    && pointers < buffer_image_pointers.len() =>
            {
                buffer_image_pointers[pointers] = operand(0);
                let image = buffer_images[..images]
                    .iter()
                    .position(|&i| i == operand(2))
                    .expect("matched above");
                pointer_rgba32f[pointers] = rgba32f[image];
                pointers += 1;
            }
            OP_VARIABLE
                if operands >= 3 && buffer_image_pointers[..pointers].contains(&operand(0)) =>
            {
                if let Some(binding) = binding_of(bytes, operand(1)) {
                    if binding < 64 {
                        facts.texel_mask |= 1 << binding;
                        let pointer = buffer_image_pointers[..pointers]
                            .iter()
                            .position(|&q| q == operand(0))
                            .expect("matched above");
                        if pointer_rgba32f[pointer] {
                            facts.texel4_mask |= 1 << binding;
                        }
                    }
                }
            }
            OP_DECORATE if operands >= 2 && operand(1) == DECORATION_NON_WRITABLE => {
                if let Some(binding) = binding_of(bytes, operand(0)) {
                    if binding < 64 {
                        facts.read_only_mask |= 1 << binding;
                    }
                }
            }
            _ => {}
        }
        at += count;
    }
    Ok(facts)
}

/// Calls `f(opcode, first operand word index, operand count)` for every instruction of
/// a module `inspect` has accepted; stops early when `f` returns `Some`.
fn find_instruction<T>(
    bytes: &[u8],
    mut f: impl FnMut(u32, usize, usize) -> Option<T>,
) -> Option<T> {
    let len = bytes.len() / 4;
    let mut at = 5;
    while at < len {
        let head = word(bytes, at);
        let count = (head >> 16) as usize;
        if count == 0 || at + count > len {
            return None;
        }
        if let Some(found) = f(head & 0xffff, at + 1, count - 1) {
            return Some(found);
        }
        at += count;
    }
    None
}

/// The binding number the variable `id` is decorated with, if any.
fn binding_of(bytes: &[u8], id: u32) -> Option<u32> {
    find_instruction(bytes, |op, first, operands| {
        (op == OP_DECORATE
            && operands >= 3
            && word(bytes, first) == id
            && word(bytes, first + 1) == DECORATION_BINDING)
            .then(|| word(bytes, first + 2))
    })
}

/// The `OpName` of the variable decorated `Binding binding` (the kernel parameter's
/// name when the module was built with rust-gpu's `NameVariables` metadata), without
/// its terminating nul; `None` when the binding or its name is absent.
pub fn binding_name(bytes: &[u8], binding: u32) -> Option<&[u8]> {
    let id = find_instruction(bytes, |op, first, operands| {
        (op == OP_DECORATE
            && operands >= 3
            && word(bytes, first + 1) == DECORATION_BINDING
            && word(bytes, first + 2) == binding)
            .then(|| word(bytes, first))
    })?;
    find_instruction(bytes, |op, first, operands| {
        if op != OP_NAME || operands < 2 || word(bytes, first) != id {
            return None;
        }
        let tail = &bytes[(first + 1) * 4..(first + operands) * 4];
        let end = tail.iter().position(|&b| b == 0).unwrap_or(tail.len());
        Some(&tail[..end])
    })
}

impl ModuleFacts {
    /// The bytes of the (last) entry point's name, without the terminating nul.
    pub fn entry_point_name<'a>(&self, bytes: &'a [u8]) -> &'a [u8] {
        if self.entry_points == 0 {
            return &[];
        }
        let tail = &bytes[self.name_at * 4..];
        let end = tail.iter().position(|&b| b == 0).unwrap_or(tail.len());
        &tail[..end]
    }

    /// `Some(n)` when the bindings are exactly `0..n` (the drape convention).
    pub fn contiguous_binding_count(&self) -> Option<u32> {
        let n = self.binding_mask.count_ones();
        let expected = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
        (self.binding_mask == expected).then_some(n)
    }
}
