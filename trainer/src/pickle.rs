//! The subset of Python's pickle that NumPy object arrays use: enough to write
//! `annots.npy` and `smpl_params/*.npy` as `numpy.save` would (a 0-d object array
//! holding dicts, lists, strings and float arrays), and to read back what NumPy
//! writes (protocols 2 to 5). Arrays inside become [`npy::Array`]s.

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
            PyValue::Dict(items) => items.iter().find(|(k, _)| matches!(k, PyValue::Str(s) if s == key)).map(|(_, v)| v),
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
        PyValue::Dict(items.into_iter().map(|(k, v)| (PyValue::Str(k.to_string()), v)).collect())
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

/// What the reader keeps on its stack: values, plus the callables and half-built
/// objects of NumPy's reduce protocol.
#[derive(Clone, Debug, PartialEq)]
enum Obj {
    Mark,
    Value(PyValue),
    Global(String, String),
    Tuple(Vec<Obj>),
    /// `numpy.dtype(code, ...)`, before its state.
    DtypeCall(String),
    /// A dtype: byte order + code, e.g. "<f8", "|O8".
    Dtype(String),
    /// `_reconstruct(ndarray, ...)`, before its state.
    EmptyArray,
}

fn into_value(o: Obj) -> Result<PyValue, PickleProblem> {
    match o {
        Obj::Value(v) => Ok(v),
        Obj::Tuple(items) => Ok(PyValue::Tuple(items.into_iter().map(into_value).collect::<Result<_, _>>()?)),
        other => Err(PickleProblem::NotAValue { found: format!("{other:?}") }),
    }
}

/// A pickle that cannot be read: the file (or what the bytes are), the byte offset of
/// the opcode at fault (or where the bytes ran out; None for the `.npy` wrapper around
/// the pickle) and the problem.
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
            (Some(at), PickleProblem::Truncated) => write!(f, "{file}: pickle truncated at byte {at}"),
            (Some(at), problem) => write!(f, "{file}: pickle at byte {at}: {problem}"),
            (None, problem) => write!(f, "{file}: {problem}"),
        }
    }
}

impl std::error::Error for PickleError {}

/// What is wrong with a pickle ([`PickleError::problem`]).
#[derive(Debug, thiserror::Error)]
pub enum PickleProblem {
    /// The bytes end inside an opcode or its argument.
    #[error("pickle truncated")]
    Truncated,
    /// STOP with nothing on the stack.
    #[error("empty pickle")]
    Empty,
    /// An opcode this reader does not implement.
    #[error("unsupported opcode 0x{opcode:02x}")]
    UnsupportedOpcode { opcode: u8 },
    /// An opcode (by its name in the pickle protocol) that does not fit what precedes
    /// it: no MARK, a short or empty stack, a list or dict operation on something else.
    #[error("{op} {problem}")]
    Opcode { op: &'static str, problem: &'static str },
    /// A string whose bytes are not UTF-8.
    #[error("string is not UTF-8")]
    NotUtf8,
    /// A GET of a memo key no PUT or MEMOIZE stored.
    #[error("unknown memo key {key}")]
    UnknownMemo { key: u32 },
    /// A REDUCE of something this reader does not call (it calls NumPy's
    /// `_reconstruct` and `dtype`, and `_codecs.encode`).
    #[error("cannot call {callable}")]
    Call { callable: String },
    /// Arguments a callable this reader knows cannot take.
    #[error("{call} {problem}")]
    Arguments { call: &'static str, problem: &'static str },
    /// A BUILD of an object that takes no state.
    #[error("cannot BUILD {target}")]
    Build { target: String },
    /// A callable or a half-built object where a value belongs.
    #[error("expected a value, found {found}")]
    NotAValue { found: String },
    /// An ndarray state `(version, shape, dtype, fortran, data)` with `items` entries.
    #[error("array state has {items} items, expected 5")]
    ArrayState { items: usize },
    /// An ndarray state this reader does not take (a bad shape, Fortran order, no dtype,
    /// data of the wrong kind).
    #[error("{problem}")]
    Array { problem: &'static str },
    /// An array's bytes that do not decode as its dtype and shape.
    #[error("{error}")]
    ArrayData { error: npy::NpyError },
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

/// Decodes a pickle into a value; `what` names it in errors.
pub fn decode(bytes: &[u8], what: &str) -> Result<PyValue, PickleError> {
    let fail = |at: usize, problem: PickleProblem| PickleError { file: what.to_string(), at: Some(at), problem };
    let mut stack: Vec<Obj> = Vec::new();
    let mut memo: std::collections::HashMap<u32, Obj> = Default::default();
    let mut at = 0usize;
    macro_rules! take {
        ($n:expr) => {{
            let n: usize = $n;
            if at + n > bytes.len() {
                return Err(fail(at, PickleProblem::Truncated));
            }
            let s = &bytes[at..at + n];
            at += n;
            s
        }};
    }
    fn pop_mark(stack: &mut Vec<Obj>) -> Option<Vec<Obj>> {
        let pos = stack.iter().rposition(|i| *i == Obj::Mark)?;
        let items = stack.split_off(pos + 1);
        stack.pop();
        Some(items)
    }
    loop {
        let op_at = at;
        let op = take!(1)[0];
        let e = |p: PickleProblem| fail(op_at, p);
        let bad = |op: &'static str, problem: &'static str| fail(op_at, PickleProblem::Opcode { op, problem });
        match op {
            0x80 => {
                take!(1);
            }
            0x95 => {
                take!(8);
            }
            b'.' => break,
            b'(' => stack.push(Obj::Mark),
            b'N' => stack.push(Obj::Value(PyValue::None)),
            0x88 => stack.push(Obj::Value(PyValue::Bool(true))),
            0x89 => stack.push(Obj::Value(PyValue::Bool(false))),
            b'K' => stack.push(Obj::Value(PyValue::Int(i64::from(take!(1)[0])))),
            b'M' => {
                let b = take!(2);
                stack.push(Obj::Value(PyValue::Int(i64::from(u16::from_le_bytes([b[0], b[1]])))));
            }
            b'J' => {
                let b = take!(4);
                stack.push(Obj::Value(PyValue::Int(i64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])))));
            }
            0x8a => {
                let n = take!(1)[0] as usize;
                let b = take!(n);
                let mut v: i64 = 0;
                for (i, &x) in b.iter().enumerate().take(8) {
                    v |= i64::from(x) << (8 * i);
                }
                if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                    v -= 1i64 << (8 * n);
                }
                stack.push(Obj::Value(PyValue::Int(v)));
            }
            b'G' => {
                let b = take!(8);
                stack.push(Obj::Value(PyValue::Float(f64::from_be_bytes(b.try_into().expect("8 bytes")))));
            }
            b'X' | 0x8d | 0x8c => {
                let n = match op {
                    b'X' => u32::from_le_bytes(take!(4).try_into().expect("4")) as usize,
                    0x8d => u64::from_le_bytes(take!(8).try_into().expect("8")) as usize,
                    _ => take!(1)[0] as usize,
                };
                let s = std::str::from_utf8(take!(n)).map_err(|_| e(PickleProblem::NotUtf8))?;
                stack.push(Obj::Value(PyValue::Str(s.to_string())));
            }
            b'B' | b'C' | 0x8e => {
                let n = match op {
                    b'B' => u32::from_le_bytes(take!(4).try_into().expect("4")) as usize,
                    0x8e => u64::from_le_bytes(take!(8).try_into().expect("8")) as usize,
                    _ => take!(1)[0] as usize,
                };
                stack.push(Obj::Value(PyValue::Bytes(take!(n).to_vec())));
            }
            b')' => stack.push(Obj::Tuple(vec![])),
            b']' => stack.push(Obj::Value(PyValue::List(vec![]))),
            b'}' => stack.push(Obj::Value(PyValue::Dict(vec![]))),
            b't' => {
                let items = pop_mark(&mut stack).ok_or_else(|| bad("TUPLE", "without MARK"))?;
                stack.push(Obj::Tuple(items));
            }
            0x85..=0x87 => {
                let n = (op - 0x84) as usize;
                if stack.len() < n {
                    return Err(bad(["TUPLE1", "TUPLE2", "TUPLE3"][n - 1], "on a short stack"));
                }
                let items = stack.split_off(stack.len() - n);
                stack.push(Obj::Tuple(items));
            }
            b'a' | b'e' => {
                let items = if op == b'a' { vec![stack.pop().ok_or_else(|| bad("APPEND", "on empty stack"))?] } else { pop_mark(&mut stack).ok_or_else(|| bad("APPENDS", "without MARK"))? };
                let values: Vec<PyValue> = items.into_iter().map(into_value).collect::<Result<_, _>>().map_err(e)?;
                match stack.last_mut() {
                    Some(Obj::Value(PyValue::List(l))) => l.extend(values),
                    _ => return Err(bad("APPEND", "to a non-list")),
                }
            }
            b's' | b'u' => {
                let items = if op == b's' {
                    if stack.len() < 3 {
                        return Err(bad("SETITEM", "on a short stack"));
                    }
                    stack.split_off(stack.len() - 2)
                } else {
                    pop_mark(&mut stack).ok_or_else(|| bad("SETITEMS", "without MARK"))?
                };
                let values: Vec<PyValue> = items.into_iter().map(into_value).collect::<Result<_, _>>().map_err(e)?;
                match stack.last_mut() {
                    Some(Obj::Value(PyValue::Dict(d))) => d.extend(values.chunks_exact(2).map(|kv| (kv[0].clone(), kv[1].clone()))),
                    _ => return Err(bad("SETITEM", "to a non-dict")),
                }
            }
            b'c' => {
                // GLOBAL: module and name, each ended by a newline.
                let mut lines = [String::new(), String::new()];
                for line in &mut lines {
                    let end = bytes[at..].iter().position(|&b| b == b'\n').ok_or_else(|| bad("GLOBAL", "without newline"))?;
                    *line = String::from_utf8_lossy(&bytes[at..at + end]).into_owned();
                    at += end + 1;
                }
                let [module, name] = lines;
                stack.push(Obj::Global(module, name));
            }
            0x93 => match (stack.pop(), stack.pop()) {
                (Some(Obj::Value(PyValue::Str(n))), Some(Obj::Value(PyValue::Str(m)))) => stack.push(Obj::Global(m, n)),
                _ => return Err(bad("STACK_GLOBAL", "needs two strings")),
            },
            0x94 => {
                let top = stack.last().cloned().ok_or_else(|| bad("MEMOIZE", "on empty stack"))?;
                memo.insert(memo.len() as u32, top);
            }
            b'q' | b'r' => {
                let key = if op == b'q' { u32::from(take!(1)[0]) } else { u32::from_le_bytes(take!(4).try_into().expect("4")) };
                let top = stack.last().cloned().ok_or_else(|| bad("PUT", "on empty stack"))?;
                memo.insert(key, top);
            }
            b'h' | b'j' => {
                let key = if op == b'h' { u32::from(take!(1)[0]) } else { u32::from_le_bytes(take!(4).try_into().expect("4")) };
                stack.push(memo.get(&key).cloned().ok_or_else(|| e(PickleProblem::UnknownMemo { key }))?);
            }
            b'R' => {
                let args = stack.pop().ok_or_else(|| bad("REDUCE", "without arguments"))?;
                let callable = stack.pop().ok_or_else(|| bad("REDUCE", "without a callable"))?;
                let arguments = |call: &'static str, problem: &'static str| e(PickleProblem::Arguments { call, problem });
                match callable {
                    Obj::Global(m, n) if m.ends_with("multiarray") && n == "_reconstruct" => stack.push(Obj::EmptyArray),
                    Obj::Global(m, n) if m == "numpy" && n == "dtype" => {
                        let code = match args {
                            Obj::Tuple(t) => match t.first() {
                                Some(Obj::Value(PyValue::Str(s))) => s.clone(),
                                _ => return Err(arguments("dtype()", "without a type code")),
                            },
                            _ => return Err(arguments("dtype()", "arguments are not a tuple")),
                        };
                        stack.push(Obj::DtypeCall(code));
                    }
                    Obj::Global(m, n) if m == "_codecs" && n == "encode" => {
                        // Protocol 2 bytes: _codecs.encode(text, 'latin1').
                        let Obj::Tuple(t) = args else { return Err(arguments("encode()", "arguments are not a tuple")) };
                        let Some(Obj::Value(PyValue::Str(text))) = t.first() else { return Err(arguments("encode()", "of a non-string")) };
                        stack.push(Obj::Value(PyValue::Bytes(text.chars().map(|c| c as u32 as u8).collect())));
                    }
                    Obj::Global(m, n) => return Err(e(PickleProblem::Call { callable: format!("{m}.{n}") })),
                    other => return Err(e(PickleProblem::Call { callable: format!("{other:?}") })),
                }
            }
            b'b' => {
                let state = stack.pop().ok_or_else(|| bad("BUILD", "on empty stack"))?;
                let target = stack.pop().ok_or_else(|| bad("BUILD", "without an object"))?;
                match (target, state) {
                    (Obj::DtypeCall(code), Obj::Tuple(t)) => {
                        let order = match t.get(1) {
                            Some(Obj::Value(PyValue::Str(o))) => o.clone(),
                            _ => "|".into(),
                        };
                        stack.push(Obj::Dtype(format!("{order}{code}")));
                    }
                    (Obj::EmptyArray, Obj::Tuple(t)) => stack.push(Obj::Value(build_array(t).map_err(e)?)),
                    (t, _) => return Err(e(PickleProblem::Build { target: format!("{t:?}") })),
                }
            }
            other => return Err(e(PickleProblem::UnsupportedOpcode { opcode: other })),
        }
    }
    into_value(stack.pop().ok_or_else(|| fail(at, PickleProblem::Empty))?).map_err(|p| fail(at, p))
}

/// An ndarray from its state `(version, shape, dtype, fortran, data)`.
fn build_array(state: Vec<Obj>) -> Result<PyValue, PickleProblem> {
    let array = |problem: &'static str| PickleProblem::Array { problem };
    let [_, shape, dtype, fortran, data] = <[Obj; 5]>::try_from(state).map_err(|s| PickleProblem::ArrayState { items: s.len() })?;
    let shape: Vec<usize> = match into_value(shape)? {
        PyValue::Tuple(t) => t.iter().map(|d| match d { PyValue::Int(i) if *i >= 0 => Ok(*i as usize), _ => Err(array("bad shape")) }).collect::<Result<_, _>>()?,
        _ => return Err(array("array shape is not a tuple")),
    };
    if fortran == Obj::Value(PyValue::Bool(true)) {
        return Err(array("Fortran-order arrays are not supported"));
    }
    let Obj::Dtype(descr) = dtype else { return Err(array("array dtype missing")) };
    if descr.ends_with('O') || descr.ends_with("O8") {
        let items = match into_value(data)? {
            PyValue::List(l) => l,
            _ => return Err(array("object array data is not a list")),
        };
        // A 0-d object array is how numpy.save stores a dict: unwrap it.
        if shape.is_empty() && items.len() == 1 {
            return Ok(items.into_iter().next().expect("one item"));
        }
        return Ok(PyValue::List(items));
    }
    let bytes = match into_value(data)? {
        PyValue::Bytes(b) => b,
        _ => return Err(array("array data is not bytes")),
    };
    // Reuse the .npy decoder on a synthesized header.
    let shape_text = match shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", shape[0]),
        _ => format!("({})", shape.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")),
    };
    let header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_text}, }}\n");
    let mut npy_bytes = b"\x93NUMPY\x01\x00".to_vec();
    npy_bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy_bytes.extend_from_slice(header.as_bytes());
    npy_bytes.extend_from_slice(&bytes);
    npy::decode(&npy_bytes, "pickled array", None).map(PyValue::Array).map_err(|error| PickleProblem::ArrayData { error })
}

/// Reads a `.npy` holding a pickled object (as `numpy.save` writes a dict).
pub fn decode_object_npy(bytes: &[u8], what: &str) -> Result<PyValue, PickleError> {
    let wrapper = |problem: PickleProblem| PickleError { file: what.to_string(), at: None, problem };
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(wrapper(PickleProblem::NotNpy));
    }
    if bytes[6] != 1 && bytes.len() < 12 {
        return Err(wrapper(PickleProblem::NpyHeaderTruncated));
    }
    let (len, start) = if bytes[6] == 1 { (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10) } else { (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12) };
    if bytes.len() < start + len {
        return Err(wrapper(PickleProblem::NpyHeaderTruncated));
    }
    let header = String::from_utf8_lossy(&bytes[start..start + len]);
    if !header.contains("'|O'") {
        return Err(wrapper(PickleProblem::NotObjectArray { header: header.trim().to_string() }));
    }
    decode(&bytes[start + len..], what)
}
