//! The subset of Python's pickle that NumPy object arrays use: enough to write
//! `annots.npy` and `smpl_params/*.npy` as `numpy.save` would (a 0-d object array
//! holding dicts, lists, strings and float arrays), and to read back what NumPy 1.x
//! and 2.x write (protocols 2 to 5, protocol 5's `_frombuffer` arrays included) with
//! Python's semantics: memo entries are references to one object. Arrays inside become
//! [`npy::Array`]s. Hostile input is refused, never a panic: reads are bounds-checked,
//! nesting and the size of what is built are capped.

use crate::npy::{self, Array, Dtype};

/// A Python value.
#[derive(Clone, Debug, PartialEq)]
pub enum PyValue {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<PyValue>),
    Tuple(Vec<PyValue>),
    /// Key order kept.
    Dict(Vec<(PyValue, PyValue)>),
    Array(Array),
}

impl PyValue {
    /// `dict[key]` for a string key.
    pub fn get(&self, key: &str) -> Option<&PyValue> {
        match self {
            PyValue::Dict(items) => items
                .iter()
                .find(|(k, _)| matches!(k, PyValue::Str(s) if s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    pub fn as_list(&self) -> Option<&[PyValue]> {
        match self {
            PyValue::List(v) | PyValue::Tuple(v) => Some(v),
            _ => None,
        }
    }

    pub fn as_array(&self) -> Option<&Array> {
        match self {
            PyValue::Array(a) => Some(a),
            _ => None,
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match self {
            PyValue::Str(s) => Some(s),
            _ => None,
        }
    }

    /// A dict with string keys.
    pub fn dict(items: Vec<(&str, PyValue)>) -> Self {
        PyValue::Dict(
            items
                .into_iter()
                .map(|(k, v)| (PyValue::Str(k.to_string()), v))
                .collect(),
        )
    }
}

// ---- writing (protocol 3, what numpy.save uses) ----

fn put_str(out: &mut Vec<u8>, s: &str) {
    out.push(b'X');
    out.extend_from_slice(&(s.len() as u32).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

fn put_int(out: &mut Vec<u8>, v: i64) {
    if (0..256).contains(&v) {
        out.push(b'K');
        out.push(v as u8);
    } else if i32::try_from(v).is_ok() {
        out.push(b'J');
        out.extend_from_slice(&(v as i32).to_le_bytes());
    } else {
        out.push(0x8a); // LONG1
        out.push(8);
        out.extend_from_slice(&v.to_le_bytes());
    }
}

fn put_global(out: &mut Vec<u8>, module: &str, name: &str) {
    out.push(b'c');
    out.extend_from_slice(module.as_bytes());
    out.push(b'\n');
    out.extend_from_slice(name.as_bytes());
    out.push(b'\n');
}

/// `numpy.dtype(code, False, True)` with its state.
fn put_dtype(out: &mut Vec<u8>, code: &str, byteorder: &str, flags: i64) {
    put_global(out, "numpy", "dtype");
    put_str(out, code);
    out.extend_from_slice(&[0x89, 0x88, 0x87, b'R']); // False, True, TUPLE3, REDUCE
    out.push(b'(');
    put_int(out, 3);
    put_str(out, byteorder);
    out.extend_from_slice(b"NNN");
    put_int(out, -1);
    put_int(out, -1);
    put_int(out, flags);
    out.extend_from_slice(b"tb"); // TUPLE, BUILD
}

fn put_shape(out: &mut Vec<u8>, shape: &[usize]) {
    out.push(b'(');
    for &d in shape {
        put_int(out, d as i64);
    }
    out.push(b't');
}

/// `_reconstruct(ndarray, (0,), b'b')` followed by BUILD with `state`.
fn put_array_head(out: &mut Vec<u8>) {
    put_global(out, "numpy.core.multiarray", "_reconstruct");
    put_global(out, "numpy", "ndarray");
    put_int(out, 0);
    out.push(0x85); // TUPLE1
    out.extend_from_slice(&[b'C', 1, b'b']); // SHORT_BINBYTES b'b'
    out.extend_from_slice(&[0x87, b'R']);
}

fn put_value(out: &mut Vec<u8>, v: &PyValue) {
    match v {
        PyValue::None => out.push(b'N'),
        PyValue::Bool(b) => out.push(if *b { 0x88 } else { 0x89 }),
        PyValue::Int(i) => put_int(out, *i),
        PyValue::Float(f) => {
            out.push(b'G');
            out.extend_from_slice(&f.to_be_bytes());
        }
        PyValue::Str(s) => put_str(out, s),
        PyValue::Bytes(b) => {
            out.push(b'B');
            out.extend_from_slice(&(b.len() as u32).to_le_bytes());
            out.extend_from_slice(b);
        }
        PyValue::List(items) => {
            out.push(b']');
            if !items.is_empty() {
                out.push(b'(');
                for x in items {
                    put_value(out, x);
                }
                out.push(b'e');
            }
        }
        PyValue::Tuple(items) => {
            out.push(b'(');
            for x in items {
                put_value(out, x);
            }
            out.push(b't');
        }
        PyValue::Dict(items) => {
            out.push(b'}');
            if !items.is_empty() {
                out.push(b'(');
                for (k, x) in items {
                    put_value(out, k);
                    put_value(out, x);
                }
                out.push(b'u');
            }
        }
        PyValue::Array(a) => {
            put_array_head(out);
            out.push(b'(');
            put_int(out, 1);
            put_shape(out, &a.shape);
            let (code, order) = match a.dtype {
                Dtype::F64 => ("f8", "<"),
                Dtype::F32 => ("f4", "<"),
                Dtype::I64 => ("i8", "<"),
                Dtype::I32 => ("i4", "<"),
                Dtype::U32 => ("u4", "<"),
                Dtype::U8 => ("u1", "|"),
                Dtype::Bool => ("b1", "|"),
            };
            put_dtype(out, code, order, 0);
            out.push(0x89); // not Fortran order
            let body = npy::encode(a);
            let header_len = u16::from_le_bytes([body[8], body[9]]) as usize;
            put_value(out, &PyValue::Bytes(body[10 + header_len..].to_vec()));
            out.extend_from_slice(b"tb");
        }
    }
}

/// `.npy` bytes of a 0-d object array holding `value`, as `numpy.save(path, value)`
/// writes for a dict.
pub fn encode_object_npy(value: &PyValue) -> Vec<u8> {
    let mut pickle = vec![0x80, 3];
    put_array_head(&mut pickle);
    pickle.push(b'(');
    put_int(&mut pickle, 1);
    pickle.push(b')'); // shape ()
    put_dtype(&mut pickle, "O8", "|", 63);
    pickle.push(0x89);
    put_value(&mut pickle, &PyValue::List(vec![value.clone()]));
    pickle.extend_from_slice(b"tb.");
    let mut header = "{'descr': '|O', 'fortran_order': False, 'shape': (), }".to_string();
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&pickle);
    out
}

// ---- reading ----

/// Containers nested deeper than this are refused: turning the pickle's objects into
/// [`PyValue`]s recurses once per level, and a list that holds itself never ends.
const MAX_DEPTH: usize = 200;

/// What reading a pickle may build, in units of one object, one array element or 8
/// bytes of a string: this many, plus [`BUDGET_PER_BYTE`] per byte of the pickle.
/// Python shares an object that the pickle references twice; a [`PyValue`] holds a
/// copy in each place, so a few bytes of GETs could otherwise ask for any amount of
/// memory. What numpy writes for a dict of arrays builds about one unit per byte.
const BUDGET_BASE: usize = 1 << 20;
const BUDGET_PER_BYTE: usize = 4;

/// A numpy ndarray's dimensions at most (numpy's own limit).
const MAX_DIMS: usize = 64;

/// One object the pickle made, kept in the reader's arena. Containers hold arena
/// indices, as Python's containers hold references, and so do the stack and the memo:
/// APPEND, SETITEM and BUILD change the object in place and every reference sees the
/// change. NumPy relies on this: it memoises a dtype between its REDUCE and its BUILD,
/// and every later array of that dtype fetches the built dtype by GET.
#[derive(Debug)]
enum Node {
    /// None, a bool, a number, a string or bytes.
    Scalar(PyValue),
    List(Vec<usize>),
    Tuple(Vec<usize>),
    /// Key order kept.
    Dict(Vec<(usize, usize)>),
    /// A numeric ndarray.
    Array(Array),
    /// An object ndarray's items; a 0-d one (`zero_d`) holds one, which is what
    /// `numpy.save` of a dict stores.
    ObjectArray {
        zero_d: bool,
        items: Vec<usize>,
    },
    /// A GLOBAL or STACK_GLOBAL: module and name.
    Global(String, String),
    /// `numpy.dtype(code, ...)`: its byte order ("" until its BUILD sets "<", ">" or
    /// "|") and type code ("f8", "O8").
    Dtype {
        order: String,
        code: String,
    },
    /// `_reconstruct(ndarray, ...)`, before its BUILD.
    EmptyArray,
}

/// What a node is, for errors.
fn describe(node: &Node) -> String {
    match node {
        Node::Scalar(PyValue::None) => "None".into(),
        Node::Scalar(PyValue::Bool(_)) => "a bool".into(),
        Node::Scalar(PyValue::Int(i)) => format!("the int {i}"),
        Node::Scalar(PyValue::Float(f)) => format!("the float {f}"),
        Node::Scalar(PyValue::Str(_)) => "a string".into(),
        Node::Scalar(_) => "bytes".into(),
        Node::List(_) => "a list".into(),
        Node::Tuple(_) => "a tuple".into(),
        Node::Dict(_) => "a dict".into(),
        Node::Array(_) => "an array".into(),
        Node::ObjectArray { .. } => "an object array".into(),
        Node::Global(m, n) => format!("{m}.{n}"),
        Node::Dtype { order, code } => format!("dtype('{order}{code}')"),
        Node::EmptyArray => "an array before its BUILD".into(),
    }
}

/// A pickle that cannot be read: the file (or what the bytes are), the byte offset of
/// the opcode at fault (or where the bytes ran out, or the end for a result that
/// cannot be built; None for the `.npy` wrapper around the pickle) and the problem.
#[derive(Debug)]
pub struct PickleError {
    pub file: String,
    pub at: Option<usize>,
    pub problem: PickleProblem,
}

impl std::fmt::Display for PickleError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let file = &self.file;
        match (self.at, &self.problem) {
            (Some(at), PickleProblem::Truncated) => {
                write!(f, "{file}: pickle truncated at byte {at}")
            }
            (Some(at), problem) => write!(f, "{file}: pickle at byte {at}: {problem}"),
            (None, problem) => write!(f, "{file}: {problem}"),
        }
    }
}

impl std::error::Error for PickleError {}

/// What is wrong with a pickle ([`PickleError::problem`]).
#[derive(Debug, thiserror::Error)]
pub enum PickleProblem {
    /// The bytes end inside an opcode or its argument, or a length runs past the end.
    #[error("pickle truncated")]
    Truncated,
    /// STOP with nothing on the stack (above the last MARK).
    #[error("empty pickle")]
    Empty,
    /// An opcode this reader does not implement.
    #[error("unsupported opcode 0x{opcode:02x}")]
    UnsupportedOpcode { opcode: u8 },
    /// An opcode (by its name in the pickle protocol) that does not fit what precedes
    /// it: no MARK, a short or empty stack (nothing pops below a MARK), a list or dict
    /// operation on something else, an integer wider than 64 bits.
    #[error("{op} {problem}")]
    Opcode {
        op: &'static str,
        problem: &'static str,
    },
    /// A string whose bytes are not UTF-8.
    #[error("string is not UTF-8")]
    NotUtf8,
    /// A GET of a memo key no PUT or MEMOIZE stored.
    #[error("unknown memo key {key}")]
    UnknownMemo { key: u32 },
    /// A REDUCE of something this reader does not call (it calls NumPy's
    /// `_reconstruct`, `_frombuffer`, `scalar` and `dtype`, `_codecs.encode` and
    /// `bytes()`).
    #[error("cannot call {callable}")]
    Call { callable: String },
    /// Arguments a callable this reader knows cannot take.
    #[error("{call} {problem}")]
    Arguments {
        call: &'static str,
        problem: &'static str,
    },
    /// A BUILD of an object that takes no state.
    #[error("cannot BUILD {target}")]
    Build { target: String },
    /// A callable or a half-built object where a value belongs.
    #[error("expected a value, found {found}")]
    NotAValue { found: String },
    /// An ndarray state `([version,] shape, dtype, fortran, data)` with `items` entries.
    #[error("array state has {items} items, expected 4 or 5")]
    ArrayState { items: usize },
    /// An ndarray this reader does not take: a bad shape, no dtype, data of the wrong
    /// kind or size.
    #[error("{problem}")]
    Array { problem: &'static str },
    /// An array's bytes that do not decode as its dtype and shape.
    #[error("{error}")]
    ArrayData { error: npy::NpyError },
    /// Containers nested deeper than [`MAX_DEPTH`] (a list that holds itself, too).
    #[error("objects nested deeper than {limit} levels")]
    TooDeep { limit: usize },
    /// More to build than the pickle's size allows (see [`BUDGET_BASE`]): an object
    /// referenced from many places is copied into each.
    #[error("pickle expands past {limit} values")]
    TooLarge { limit: usize },
    /// The file does not start with the `.npy` magic.
    #[error("not a .npy file")]
    NotNpy,
    /// The `.npy` header runs past the end of the file.
    #[error("truncated header")]
    NpyHeaderTruncated,
    /// A `.npy` file of another dtype than object (`|O`).
    #[error("not an object array (header {header})")]
    NotObjectArray { header: String },
}

/// What is left of the budget ([`BUDGET_BASE`]).
struct Budget {
    left: usize,
    limit: usize,
}

impl Budget {
    fn charge(&mut self, units: usize) -> Result<(), PickleProblem> {
        self.left = self
            .left
            .checked_sub(units)
            .ok_or(PickleProblem::TooLarge { limit: self.limit })?;
        Ok(())
    }
}

/// Latin-1 text as bytes (how pickles of Python 3 bytes at protocol 2, and Python 2
/// strings, carry binary data); None for a character above U+00FF.
fn latin1_bytes(text: &str) -> Option<Vec<u8>> {
    text.chars()
        .map(|c| u8::try_from(u32::from(c)).ok())
        .collect()
}

/// A little-endian two's-complement integer of at most 8 bytes (LONG1, LONG4).
fn long_le(b: &[u8]) -> Option<i64> {
    if b.len() > 8 {
        return None;
    }
    let mut full = if b.last().is_some_and(|x| x & 0x80 != 0) {
        [0xff; 8]
    } else {
        [0; 8]
    };
    full[..b.len()].copy_from_slice(b);
    Some(i64::from_le_bytes(full))
}

/// `numpy.core.<sub>` (numpy 1.x) or `numpy._core.<sub>` (numpy 2.x).
fn numpy_core(module: &str, sub: &str) -> bool {
    module
        .strip_prefix("numpy.core.")
        .or_else(|| module.strip_prefix("numpy._core."))
        == Some(sub)
}

/// A numeric array of dtype `descr` ("<f8") and `shape` from its bytes, in C order or
/// (`fortran`) with the first index fastest. The bytes must be exactly what the shape
/// and dtype take.
fn make_array(
    descr: &str,
    shape: &[usize],
    fortran: bool,
    data: &[u8],
) -> Result<Array, PickleProblem> {
    let array = |problem: &'static str| PickleProblem::Array { problem };
    if shape.len() > MAX_DIMS {
        return Err(array("array has more than 64 dimensions"));
    }
    let count = shape
        .iter()
        .try_fold(1usize, |n, &d| n.checked_mul(d))
        .ok_or(array("array shape is too large"))?;
    // The item size is the type code's number ("f8", "u1"); npy refuses other codes.
    let digits = descr.trim_start_matches(|c: char| !c.is_ascii_digit());
    if let Ok(size) = digits.parse::<usize>() {
        if count.checked_mul(size) != Some(data.len()) {
            return Err(array("array data does not match its shape and dtype"));
        }
    }
    // Reuse the .npy decoder on a synthesized header.
    let shape_text = match shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", shape[0]),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let order = if fortran { "True" } else { "False" };
    let header =
        format!("{{'descr': '{descr}', 'fortran_order': {order}, 'shape': {shape_text}, }}\n");
    let header_len = u16::try_from(header.len()).map_err(|_| array("array dtype is too long"))?;
    let mut npy_bytes = b"\x93NUMPY\x01\x00".to_vec();
    npy_bytes.extend_from_slice(&header_len.to_le_bytes());
    npy_bytes.extend_from_slice(header.as_bytes());
    npy_bytes.extend_from_slice(data);
    npy::decode(&npy_bytes, "pickled array", None)
        .map_err(|error| PickleProblem::ArrayData { error })
}

/// The pickle machine: its input, arena, stack, MARKs and memo.
struct Reader<'a> {
    bytes: &'a [u8],
    /// The next byte to read.
    at: usize,
    arena: Vec<Node>,
    /// Arena indices.
    stack: Vec<usize>,
    /// The stack's length at each open MARK; nothing pops below the last one.
    marks: Vec<usize>,
    memo: std::collections::HashMap<u32, usize>,
    budget: Budget,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        let limit = BUDGET_BASE.saturating_add(bytes.len().saturating_mul(BUDGET_PER_BYTE));
        Self {
            bytes,
            at: 0,
            arena: Vec::new(),
            stack: Vec::new(),
            marks: Vec::new(),
            memo: Default::default(),
            budget: Budget { left: limit, limit },
        }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], PickleProblem> {
        if n > self.bytes.len() - self.at {
            return Err(PickleProblem::Truncated);
        }
        let bytes: &'a [u8] = self.bytes;
        let s = &bytes[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }

    fn byte(&mut self) -> Result<u8, PickleProblem> {
        Ok(self.take(1)?[0])
    }

    fn u32(&mut self) -> Result<u32, PickleProblem> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }

    /// An 8-byte length; one past what this machine can address is past the end.
    fn u64_len(&mut self) -> Result<usize, PickleProblem> {
        usize::try_from(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
        .map_err(|_| PickleProblem::Truncated)
    }

    /// A GLOBAL argument: text up to a newline.
    fn line(&mut self) -> Result<String, PickleProblem> {
        let bytes: &'a [u8] = self.bytes;
        let rest = &bytes[self.at..];
        let end = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or(PickleProblem::Opcode {
                op: "GLOBAL",
                problem: "without newline",
            })?;
        self.at += end + 1;
        Ok(String::from_utf8_lossy(&rest[..end]).into_owned())
    }

    fn push(&mut self, node: Node) {
        self.arena.push(node);
        self.stack.push(self.arena.len() - 1);
    }

    fn push_value(&mut self, value: PyValue) {
        self.push(Node::Scalar(value));
    }

    fn fence(&self) -> usize {
        self.marks.last().copied().unwrap_or(0)
    }

    fn pop(&mut self, op: &'static str) -> Result<usize, PickleProblem> {
        if self.stack.len() <= self.fence() {
            return Err(PickleProblem::Opcode {
                op,
                problem: "on an empty stack",
            });
        }
        Ok(self.stack.pop().expect("above the fence"))
    }

    fn top(&self, op: &'static str) -> Result<usize, PickleProblem> {
        if self.stack.len() <= self.fence() {
            return Err(PickleProblem::Opcode {
                op,
                problem: "on an empty stack",
            });
        }
        Ok(*self.stack.last().expect("above the fence"))
    }

    fn pop_n(&mut self, n: usize, op: &'static str) -> Result<Vec<usize>, PickleProblem> {
        if self.stack.len() - self.fence() < n {
            return Err(PickleProblem::Opcode {
                op,
                problem: "on a short stack",
            });
        }
        Ok(self.stack.split_off(self.stack.len() - n))
    }

    /// What was pushed since the last MARK, and that MARK gone.
    fn pop_mark(&mut self, op: &'static str) -> Result<Vec<usize>, PickleProblem> {
        let mark = self.marks.pop().ok_or(PickleProblem::Opcode {
            op,
            problem: "without MARK",
        })?;
        Ok(self.stack.split_off(mark))
    }

    fn str_at(&self, i: usize) -> Option<&str> {
        match &self.arena[i] {
            Node::Scalar(PyValue::Str(s)) => Some(s),
            _ => None,
        }
    }

    fn tuple_at(&self, i: usize) -> Option<&[usize]> {
        match &self.arena[i] {
            Node::Tuple(t) => Some(t),
            _ => None,
        }
    }

    /// Binary data: bytes, or latin-1 text (Python 2 strings, read as
    /// `np.load(encoding='latin1')` reads them).
    fn data_at(&self, i: usize) -> Option<std::borrow::Cow<'_, [u8]>> {
        match &self.arena[i] {
            Node::Scalar(PyValue::Bytes(b)) => Some(std::borrow::Cow::Borrowed(b)),
            Node::Scalar(PyValue::Str(s)) => latin1_bytes(s).map(std::borrow::Cow::Owned),
            _ => None,
        }
    }

    /// A dtype's `.npy` descr ("<f8").
    fn descr_at(&self, i: usize) -> Option<String> {
        match &self.arena[i] {
            Node::Dtype { order, code } => Some(format!("{order}{code}")),
            _ => None,
        }
    }

    /// A shape: a tuple of sizes.
    fn shape_at(&self, i: usize) -> Result<Vec<usize>, PickleProblem> {
        let array = |problem: &'static str| PickleProblem::Array { problem };
        let t = self
            .tuple_at(i)
            .ok_or(array("array shape is not a tuple"))?;
        t.iter()
            .map(|&d| match &self.arena[d] {
                Node::Scalar(PyValue::Int(n)) => {
                    usize::try_from(*n).map_err(|_| array("bad shape"))
                }
                _ => Err(array("bad shape")),
            })
            .collect()
    }

    fn add_array(&mut self, array: Array) -> Result<Node, PickleProblem> {
        self.budget.charge(array.data.len())?;
        Ok(Node::Array(array))
    }

    /// BUILD of an `_reconstruct`ed ndarray: `([version,] shape, dtype, fortran, data)`.
    fn array_from_state(&mut self, state: usize) -> Result<Node, PickleProblem> {
        let array = |problem: &'static str| PickleProblem::Array { problem };
        let t = self
            .tuple_at(state)
            .ok_or(array("array state is not a tuple"))?;
        let (shape, dtype, fortran, data) = match t {
            [_, s, d, f, x] | [s, d, f, x] => (*s, *d, *f, *x),
            _ => return Err(PickleProblem::ArrayState { items: t.len() }),
        };
        let shape = self.shape_at(shape)?;
        let fortran = matches!(self.arena[fortran], Node::Scalar(PyValue::Bool(true)));
        let descr = self.descr_at(dtype).ok_or(array("array dtype missing"))?;
        if descr
            .trim_start_matches(['<', '>', '|', '='])
            .starts_with('O')
        {
            let Node::List(items) = &self.arena[data] else {
                return Err(array("object array data is not a list"));
            };
            let items = items.clone();
            self.budget.charge(items.len())?;
            return Ok(Node::ObjectArray {
                zero_d: shape.is_empty(),
                items,
            });
        }
        let a = make_array(
            &descr,
            &shape,
            fortran,
            &self.data_at(data).ok_or(array("array data is not bytes"))?,
        )?;
        self.add_array(a)
    }

    /// REDUCE: `callable(*args)` for the callables NumPy's pickles use.
    fn call(&mut self, callable: usize, args: usize) -> Result<Node, PickleProblem> {
        let Node::Global(module, name) = &self.arena[callable] else {
            return Err(PickleProblem::Call {
                callable: describe(&self.arena[callable]),
            });
        };
        let (module, name) = (module.clone(), name.clone());
        let arguments =
            |call: &'static str, problem: &'static str| PickleProblem::Arguments { call, problem };
        let args = self
            .tuple_at(args)
            .ok_or(arguments("REDUCE", "arguments are not a tuple"))?
            .to_vec();
        match (module.as_str(), name.as_str()) {
            (m, "_reconstruct") if numpy_core(m, "multiarray") => Ok(Node::EmptyArray),
            ("numpy", "dtype") => {
                let code = args
                    .first()
                    .and_then(|&i| self.str_at(i))
                    .ok_or(arguments("dtype()", "without a type code"))?;
                Ok(Node::Dtype {
                    order: String::new(),
                    code: code.to_string(),
                })
            }
            ("_codecs", "encode") => {
                // Protocol 2 bytes: _codecs.encode(text, 'latin1').
                let text = args
                    .first()
                    .and_then(|&i| self.str_at(i))
                    .ok_or(arguments("encode()", "of a non-string"))?;
                if !matches!(
                    args.get(1).and_then(|&i| self.str_at(i)),
                    Some("latin1" | "latin-1")
                ) {
                    return Err(arguments("encode()", "to another encoding than latin1"));
                }
                let bytes = latin1_bytes(text)
                    .ok_or(arguments("encode()", "of text that is not latin-1"))?;
                self.budget.charge(bytes.len() / 8)?;
                Ok(Node::Scalar(PyValue::Bytes(bytes)))
            }
            // Protocol 2 empty bytes: bytes().
            ("__builtin__" | "builtins", "bytes") if args.is_empty() => {
                Ok(Node::Scalar(PyValue::Bytes(Vec::new())))
            }
            (m, "_frombuffer") if numpy_core(m, "numeric") => {
                // Protocol 5 arrays: _frombuffer(buffer, dtype, shape, order).
                let [buffer, dtype, shape, order] = args[..] else {
                    return Err(arguments("_frombuffer()", "takes 4 arguments"));
                };
                let descr = self
                    .descr_at(dtype)
                    .ok_or(arguments("_frombuffer()", "without a dtype"))?;
                let shape = self.shape_at(shape)?;
                let fortran = match self.str_at(order) {
                    Some("C") => false,
                    Some("F") => true,
                    _ => return Err(arguments("_frombuffer()", "order is not 'C' or 'F'")),
                };
                let a = make_array(
                    &descr,
                    &shape,
                    fortran,
                    &self
                        .data_at(buffer)
                        .ok_or(arguments("_frombuffer()", "buffer is not bytes"))?,
                )?;
                self.add_array(a)
            }
            (m, "scalar") if numpy_core(m, "multiarray") => {
                // A numpy scalar (np.float64(x)): scalar(dtype, bytes), read as a 0-d array.
                let [dtype, data] = args[..] else {
                    return Err(arguments("scalar()", "takes 2 arguments"));
                };
                let descr = self
                    .descr_at(dtype)
                    .ok_or(arguments("scalar()", "without a dtype"))?;
                let a = make_array(
                    &descr,
                    &[],
                    false,
                    &self
                        .data_at(data)
                        .ok_or(arguments("scalar()", "data is not bytes"))?,
                )?;
                self.add_array(a)
            }
            (m, n) => Err(PickleProblem::Call {
                callable: format!("{m}.{n}"),
            }),
        }
    }

    /// BUILD: sets the state of the object on top of the stack, in place.
    fn build(&mut self) -> Result<(), PickleProblem> {
        let state = self.pop("BUILD")?;
        let target = self.top("BUILD")?;
        match &self.arena[target] {
            Node::Dtype { .. } => {
                // (version, byte order, subarray, names, fields, elsize, alignment, flags)
                let order = self
                    .tuple_at(state)
                    .and_then(|t| t.get(1))
                    .and_then(|&i| self.str_at(i))
                    .map(str::to_string);
                if let (Some(order), Node::Dtype { order: o, .. }) =
                    (order, &mut self.arena[target])
                {
                    *o = order;
                }
                Ok(())
            }
            Node::EmptyArray => {
                self.arena[target] = self.array_from_state(state)?;
                Ok(())
            }
            other => Err(PickleProblem::Build {
                target: describe(other),
            }),
        }
    }

    fn memo_key(&mut self, long: bool) -> Result<u32, PickleProblem> {
        if long {
            self.u32()
        } else {
            Ok(u32::from(self.byte()?))
        }
    }

    /// Runs one opcode; the arena index of the result at STOP.
    fn step(&mut self) -> Result<Option<usize>, PickleProblem> {
        let op = self.byte()?;
        let bad = |op: &'static str, problem: &'static str| PickleProblem::Opcode { op, problem };
        match op {
            0x80 => {
                self.take(1)?; // PROTO
            }
            0x95 => {
                self.take(8)?; // FRAME: its length only groups the opcodes that follow
            }
            b'.' => {
                if self.stack.len() <= self.fence() {
                    return Err(PickleProblem::Empty);
                }
                return Ok(self.stack.last().copied());
            }
            b'(' => self.marks.push(self.stack.len()),
            b'0' => {
                // POP: the top item, or the MARK on top.
                if self.stack.len() > self.fence() {
                    self.stack.pop();
                } else if self.marks.pop().is_none() {
                    return Err(bad("POP", "on an empty stack"));
                }
            }
            b'1' => {
                self.pop_mark("POP_MARK")?;
            }
            b'2' => {
                let top = self.top("DUP")?;
                self.stack.push(top);
            }
            b'N' => self.push_value(PyValue::None),
            0x88 => self.push_value(PyValue::Bool(true)),
            0x89 => self.push_value(PyValue::Bool(false)),
            b'K' => {
                let v = self.byte()?;
                self.push_value(PyValue::Int(i64::from(v)));
            }
            b'M' => {
                let b = self.take(2)?;
                self.push_value(PyValue::Int(i64::from(u16::from_le_bytes([b[0], b[1]]))));
            }
            b'J' => {
                let v = self.u32()? as i32;
                self.push_value(PyValue::Int(i64::from(v)));
            }
            0x8a | 0x8b => {
                let n = if op == 0x8a {
                    usize::from(self.byte()?)
                } else {
                    self.u32()? as usize
                };
                let b = self.take(n)?;
                let v = long_le(b).ok_or(bad(
                    if op == 0x8a { "LONG1" } else { "LONG4" },
                    "wider than 64 bits",
                ))?;
                self.push_value(PyValue::Int(v));
            }
            b'G' => {
                let b = self.take(8)?;
                self.push_value(PyValue::Float(f64::from_be_bytes(
                    b.try_into().expect("8 bytes"),
                )));
            }
            b'X' | 0x8c | 0x8d => {
                let n = match op {
                    b'X' => self.u32()? as usize,
                    0x8d => self.u64_len()?,
                    _ => usize::from(self.byte()?),
                };
                let s = std::str::from_utf8(self.take(n)?).map_err(|_| PickleProblem::NotUtf8)?;
                self.push_value(PyValue::Str(s.to_string()));
            }
            b'U' | b'T' => {
                // Python 2 strings (SHORT_BINSTRING, BINSTRING), as latin-1 text.
                let n = if op == b'U' {
                    usize::from(self.byte()?)
                } else {
                    self.u32()? as usize
                };
                let s = self.take(n)?.iter().map(|&b| char::from(b)).collect();
                self.push_value(PyValue::Str(s));
            }
            b'B' | b'C' | 0x8e | 0x96 => {
                // BINBYTES, SHORT_BINBYTES, BINBYTES8, BYTEARRAY8 (protocol 5 buffers).
                let n = match op {
                    b'B' => self.u32()? as usize,
                    b'C' => usize::from(self.byte()?),
                    _ => self.u64_len()?,
                };
                let b = self.take(n)?.to_vec();
                self.push_value(PyValue::Bytes(b));
            }
            b')' => self.push(Node::Tuple(Vec::new())),
            b't' => {
                let items = self.pop_mark("TUPLE")?;
                self.push(Node::Tuple(items));
            }
            0x85..=0x87 => {
                let n = usize::from(op - 0x84);
                let items = self.pop_n(n, ["TUPLE1", "TUPLE2", "TUPLE3"][n - 1])?;
                self.push(Node::Tuple(items));
            }
            b']' => self.push(Node::List(Vec::new())),
            b'l' => {
                let items = self.pop_mark("LIST")?;
                self.push(Node::List(items));
            }
            b'a' | b'e' => {
                let (name, items) = if op == b'a' {
                    ("APPEND", vec![self.pop("APPEND")?])
                } else {
                    ("APPENDS", self.pop_mark("APPENDS")?)
                };
                let list = self.top(name)?;
                match &mut self.arena[list] {
                    Node::List(l) => l.extend(items),
                    _ => return Err(bad(name, "to a non-list")),
                }
            }
            b'}' => self.push(Node::Dict(Vec::new())),
            b'd' | b's' | b'u' => {
                let (name, items) = match op {
                    b'd' => ("DICT", self.pop_mark("DICT")?),
                    b's' => ("SETITEM", self.pop_n(2, "SETITEM")?),
                    _ => ("SETITEMS", self.pop_mark("SETITEMS")?),
                };
                if items.len() % 2 != 0 {
                    return Err(bad(name, "with a key and no value"));
                }
                let pairs = items.chunks_exact(2).map(|kv| (kv[0], kv[1]));
                if op == b'd' {
                    self.push(Node::Dict(pairs.collect()));
                } else {
                    let dict = self.top(name)?;
                    match &mut self.arena[dict] {
                        Node::Dict(d) => d.extend(pairs),
                        _ => return Err(bad(name, "to a non-dict")),
                    }
                }
            }
            b'c' => {
                let module = self.line()?;
                let name = self.line()?;
                self.push(Node::Global(module, name));
            }
            0x93 => {
                let name = self.pop("STACK_GLOBAL")?;
                let module = self.pop("STACK_GLOBAL")?;
                match (self.str_at(module), self.str_at(name)) {
                    (Some(m), Some(n)) => {
                        let node = Node::Global(m.to_string(), n.to_string());
                        self.push(node);
                    }
                    _ => return Err(bad("STACK_GLOBAL", "needs two strings")),
                }
            }
            0x94 => {
                let top = self.top("MEMOIZE")?;
                let key = u32::try_from(self.memo.len())
                    .map_err(|_| bad("MEMOIZE", "with a full memo"))?;
                self.memo.insert(key, top);
            }
            b'q' | b'r' => {
                let key = self.memo_key(op == b'r')?;
                let top = self.top("PUT")?;
                self.memo.insert(key, top);
            }
            b'h' | b'j' => {
                let key = self.memo_key(op == b'j')?;
                let i = *self
                    .memo
                    .get(&key)
                    .ok_or(PickleProblem::UnknownMemo { key })?;
                self.stack.push(i);
            }
            b'R' => {
                let args = self.pop("REDUCE")?;
                let callable = self.pop("REDUCE")?;
                let node = self.call(callable, args)?;
                self.push(node);
            }
            b'b' => self.build()?,
            other => return Err(PickleProblem::UnsupportedOpcode { opcode: other }),
        }
        Ok(None)
    }
}

/// The value of arena node `i`, `depth` containers down, charged to `budget`.
fn to_value(
    arena: &[Node],
    i: usize,
    depth: usize,
    budget: &mut Budget,
) -> Result<PyValue, PickleProblem> {
    if depth > MAX_DEPTH {
        return Err(PickleProblem::TooDeep { limit: MAX_DEPTH });
    }
    budget.charge(1)?;
    let all = |items: &[usize], budget: &mut Budget| {
        items
            .iter()
            .map(|&x| to_value(arena, x, depth + 1, budget))
            .collect::<Result<Vec<_>, _>>()
    };
    Ok(match &arena[i] {
        Node::Scalar(v) => {
            if let PyValue::Str(s) = v {
                budget.charge(s.len() / 8)?;
            } else if let PyValue::Bytes(b) = v {
                budget.charge(b.len() / 8)?;
            }
            v.clone()
        }
        Node::List(items) => PyValue::List(all(items, budget)?),
        Node::Tuple(items) => PyValue::Tuple(all(items, budget)?),
        Node::Dict(pairs) => PyValue::Dict(
            pairs
                .iter()
                .map(|&(k, v)| {
                    Ok((
                        to_value(arena, k, depth + 1, budget)?,
                        to_value(arena, v, depth + 1, budget)?,
                    ))
                })
                .collect::<Result<_, PickleProblem>>()?,
        ),
        Node::Array(a) => {
            budget.charge(a.data.len())?;
            PyValue::Array(a.clone())
        }
        // A 0-d object array is how numpy.save stores a dict: unwrap it.
        Node::ObjectArray {
            zero_d: true,
            items,
        } if items.len() == 1 => to_value(arena, items[0], depth + 1, budget)?,
        Node::ObjectArray { items, .. } => PyValue::List(all(items, budget)?),
        other => {
            return Err(PickleProblem::NotAValue {
                found: describe(other),
            })
        }
    })
}

/// Decodes a pickle into a value, following Python's semantics (the memo holds
/// references: what is done to an object after it is memoised is seen through every
/// GET of it); `what` names it in errors.
pub fn decode(bytes: &[u8], what: &str) -> Result<PyValue, PickleError> {
    let fail = |at: usize, problem: PickleProblem| PickleError {
        file: what.to_string(),
        at: Some(at),
        problem,
    };
    let mut reader = Reader::new(bytes);
    loop {
        let op_at = reader.at;
        match reader.step() {
            Ok(None) => {}
            Ok(Some(result)) => {
                let Reader {
                    arena, budget, at, ..
                } = &mut reader;
                return to_value(arena, result, 0, budget).map_err(|p| fail(*at, p));
            }
            // Where the bytes ran out.
            Err(PickleProblem::Truncated) => return Err(fail(reader.at, PickleProblem::Truncated)),
            Err(problem) => return Err(fail(op_at, problem)),
        }
    }
}

/// Reads a `.npy` holding a pickled object (as `numpy.save` writes a dict).
pub fn decode_object_npy(bytes: &[u8], what: &str) -> Result<PyValue, PickleError> {
    let wrapper = |problem: PickleProblem| PickleError {
        file: what.to_string(),
        at: None,
        problem,
    };
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(wrapper(PickleProblem::NotNpy));
    }
    if bytes[6] != 1 && bytes.len() < 12 {
        return Err(wrapper(PickleProblem::NpyHeaderTruncated));
    }
    let (len, start) = if bytes[6] == 1 {
        (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10)
    } else {
        (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        )
    };
    if bytes.len() - start < len {
        return Err(wrapper(PickleProblem::NpyHeaderTruncated));
    }
    let header = String::from_utf8_lossy(&bytes[start..start + len]);
    if !header.contains("'|O'") {
        return Err(wrapper(PickleProblem::NotObjectArray {
            header: header.trim().to_string(),
        }));
    }
    decode(&bytes[start + len..], what)
}
