//! Just enough of the protobuf wire format to read an ONNX model's convolution weights at run
//! time: the graph's nodes (operator, inputs) and initializers (name, dims, element type,
//! data). Everything is borrowed from the file's bytes; a truncated or corrupt file is an
//! error that says where, never a panic.

/// A field's payload.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Value<'a> {
    /// Wire type 0.
    Varint(u64),
    /// Wire type 1.
    Fixed64,
    /// Wire type 2: bytes, string, sub-message or packed repeated field.
    Bytes(&'a [u8]),
    /// Wire type 5.
    Fixed32(u32),
}

/// Iterates over the `(field number, value)` pairs of one message.
pub(crate) struct Fields<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Fields<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, at: 0 }
    }

    fn varint(&mut self) -> Result<u64, String> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let Some(&b) = self.bytes.get(self.at) else {
                return Err(format!(
                    "truncated: a number runs past the end at byte {}",
                    self.at
                ));
            };
            self.at += 1;
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(format!(
            "corrupt: a number longer than 10 bytes at byte {}",
            self.at
        ))
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let left = self.bytes.len() - self.at;
        if n > left {
            return Err(format!(
                "truncated: a field of {n} bytes at byte {} has only {left} bytes left",
                self.at
            ));
        }
        let s = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }

    fn next_field(&mut self) -> Result<(u32, Value<'a>), String> {
        let key = self.varint()?;
        let (field, wire) = ((key >> 3) as u32, key & 7);
        let value = match wire {
            0 => Value::Varint(self.varint()?),
            1 => {
                self.take(8)?;
                Value::Fixed64
            }
            2 => {
                let n = self.varint()?;
                Value::Bytes(self.take(usize::try_from(n).unwrap_or(usize::MAX))?)
            }
            5 => Value::Fixed32(u32::from_le_bytes(
                self.take(4)?.try_into().expect("4 bytes"),
            )),
            w => {
                return Err(format!(
                    "corrupt: wire type {w} of field {field} at byte {} (not a protobuf file?)",
                    self.at
                ));
            }
        };
        Ok((field, value))
    }
}

impl<'a> Iterator for Fields<'a> {
    type Item = Result<(u32, Value<'a>), String>;

    fn next(&mut self) -> Option<Self::Item> {
        (self.at < self.bytes.len()).then(|| {
            let r = self.next_field();
            if r.is_err() {
                self.at = self.bytes.len();
            }
            r
        })
    }
}

/// A node of the graph: operator and input names.
#[derive(Clone, Debug, Default)]
pub(crate) struct Node {
    pub op_type: String,
    pub inputs: Vec<String>,
}

/// An initializer (a constant tensor of the graph).
#[derive(Clone, Debug, Default)]
pub(crate) struct Initializer<'a> {
    pub name: String,
    pub dims: Vec<usize>,
    /// ONNX `TensorProto.DataType` (1 = float, 10 = float16, 11 = double, 16 = bfloat16).
    pub data_type: i32,
    pub raw: Option<&'a [u8]>,
    pub floats: Vec<f32>,
    pub external: bool,
}

impl Initializer<'_> {
    /// The values as `f32`, checked against the dims.
    pub(crate) fn values(&self) -> Result<Vec<f32>, String> {
        if self.external {
            return Err(format!(
                "`{}` is stored in an external data file; save the model with its weights \
                 inside (onnx.save(model, path, save_as_external_data=False))",
                self.name
            ));
        }
        let count = self
            .dims
            .iter()
            .try_fold(1usize, |n, &d| n.checked_mul(d))
            .ok_or_else(|| format!("`{}` has dims {:?}: too large", self.name, self.dims))?;
        let values: Vec<f32> = match (self.data_type, self.raw) {
            (1, Some(raw)) => raw
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect(),
            (1, None) => self.floats.clone(),
            (11, Some(raw)) => raw
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")) as f32)
                .collect(),
            (10, Some(raw)) => raw
                .chunks_exact(2)
                .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
            (16, Some(raw)) => raw
                .chunks_exact(2)
                .map(|c| half::bf16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
            (t, _) => {
                return Err(format!(
                    "`{}` has ONNX element type {t}; only float32, float16, bfloat16 and \
                     float64 (as raw data) are read",
                    self.name
                ));
            }
        };
        if values.len() != count {
            return Err(format!(
                "`{}` holds {} values for dims {:?} ({count} expected): truncated or corrupt",
                self.name,
                values.len(),
                self.dims
            ));
        }
        Ok(values)
    }
}

/// The parts of an ONNX graph the weight loader needs.
#[derive(Debug, Default)]
pub(crate) struct Graph<'a> {
    pub nodes: Vec<Node>,
    pub initializers: Vec<Initializer<'a>>,
}

fn string(v: Value<'_>) -> Result<String, String> {
    match v {
        Value::Bytes(b) => Ok(String::from_utf8_lossy(b).into_owned()),
        _ => Err("corrupt: a string field with a non-string wire type".into()),
    }
}

fn payload<'a>(v: Value<'a>, what: &str) -> Result<&'a [u8], String> {
    match v {
        Value::Bytes(b) => Ok(b),
        _ => Err(format!("corrupt: {what} is not a length-delimited field")),
    }
}

/// Parses `ModelProto.graph` (field 7) of an ONNX file.
pub(crate) fn parse_model(bytes: &[u8]) -> Result<Graph<'_>, String> {
    let mut graph = None;
    for field in Fields::new(bytes) {
        if let (7, v) = field? {
            graph = Some(payload(v, "the graph")?);
        }
    }
    let graph = graph.ok_or("no ONNX graph in the file (not an ONNX model?)")?;
    let mut out = Graph::default();
    for field in Fields::new(graph) {
        match field? {
            (1, v) => out.nodes.push(parse_node(payload(v, "a node")?)?),
            (5, v) => out
                .initializers
                .push(parse_tensor(payload(v, "an initializer")?)?),
            _ => {}
        }
    }
    Ok(out)
}

fn parse_node(b: &[u8]) -> Result<Node, String> {
    let mut node = Node::default();
    for field in Fields::new(b) {
        match field? {
            (1, v) => node.inputs.push(string(v)?),
            (4, v) => node.op_type = string(v)?,
            _ => {}
        }
    }
    Ok(node)
}

fn parse_tensor(b: &[u8]) -> Result<Initializer<'_>, String> {
    let mut t = Initializer::default();
    for field in Fields::new(b) {
        match field? {
            (1, Value::Varint(d)) => t.dims.push(d as usize),
            (1, Value::Bytes(packed)) => {
                for d in Fields::packed_varints(packed)? {
                    t.dims.push(d as usize);
                }
            }
            (2, Value::Varint(d)) => t.data_type = d as i32,
            (4, Value::Fixed32(f)) => t.floats.push(f32::from_bits(f)),
            (4, Value::Bytes(packed)) => t.floats.extend(
                packed
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))),
            ),
            (8, v) => t.name = string(v)?,
            (9, v) => t.raw = Some(payload(v, "raw_data")?),
            (14, Value::Varint(1)) => t.external = true,
            _ => {}
        }
    }
    Ok(t)
}

impl Fields<'_> {
    fn packed_varints(b: &[u8]) -> Result<Vec<u64>, String> {
        let mut f = Fields::new(b);
        let mut out = Vec::new();
        while f.at < b.len() {
            out.push(f.varint()?);
        }
        Ok(out)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn half_precision_raw_data_is_read() {
        let values = |data_type: i32, bits: &[u16]| {
            let raw: Vec<u8> = bits.iter().flat_map(|b| b.to_le_bytes()).collect();
            Initializer {
                name: "w".into(),
                dims: vec![bits.len()],
                data_type,
                raw: Some(&raw),
                ..Initializer::default()
            }
            .values()
            .unwrap()
        };
        // float16: 1, −2, the nearest to 1/3, the smallest subnormal.
        assert_eq!(
            values(10, &[0x3c00, 0xc000, 0x3555, 0x0001]),
            [1.0, -2.0, 0.333_251_95, 2f32.powi(-24)]
        );
        // bfloat16: the upper half of a float32.
        assert_eq!(values(16, &[0x3f80, 0xc040]), [1.0, -3.0]);
    }

    #[test]
    fn truncation_is_reported_with_its_position() {
        // Field 7 (graph), length 10, but only 2 bytes follow.
        let err = parse_model(&[0x3a, 10, 1, 2]).unwrap_err();
        assert!(err.contains("truncated") && err.contains("byte 2"), "{err}");
        let err = parse_model(b"hello, not protobuf").unwrap_err();
        assert!(
            err.contains("corrupt") || err.contains("truncated") || err.contains("no ONNX graph"),
            "{err}"
        );
    }

    /// Protobuf encoding, for the seed model.
    fn varint(mut v: u64, out: &mut Vec<u8>) {
        loop {
            let low = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                out.push(low);
                return;
            }
            out.push(low | 0x80);
        }
    }

    fn bytes_field(field: u64, payload: &[u8], out: &mut Vec<u8>) {
        varint(field << 3 | 2, out);
        varint(payload.len() as u64, out);
        out.extend(payload);
    }

    fn varint_field(field: u64, v: u64, out: &mut Vec<u8>) {
        varint(field << 3, out);
        varint(v, out);
    }

    /// A model with one convolution: a `[2, 1, 3, 3]` float kernel as raw data, a bias as
    /// packed floats, and the Conv node that uses them.
    pub(crate) fn seed_model() -> Vec<u8> {
        let mut weight = Vec::new();
        for d in [2, 1, 3, 3] {
            varint_field(1, d, &mut weight);
        }
        varint_field(2, 1, &mut weight);
        bytes_field(8, b"w", &mut weight);
        let raw: Vec<u8> = (0..18).flat_map(|i| (i as f32).to_le_bytes()).collect();
        bytes_field(9, &raw, &mut weight);
        let mut bias = Vec::new();
        bytes_field(1, &[2], &mut bias);
        varint_field(2, 1, &mut bias);
        bytes_field(8, b"b", &mut bias);
        let packed: Vec<u8> = [0.5f32, -0.5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        bytes_field(4, &packed, &mut bias);
        let mut node = Vec::new();
        for input in ["x", "w", "b"] {
            bytes_field(1, input.as_bytes(), &mut node);
        }
        bytes_field(4, b"Conv", &mut node);
        let mut graph = Vec::new();
        bytes_field(1, &node, &mut graph);
        bytes_field(5, &weight, &mut graph);
        bytes_field(5, &bias, &mut graph);
        let mut model = Vec::new();
        varint_field(1, 8, &mut model); // ir_version
        bytes_field(7, &graph, &mut model);
        model
    }

    #[test]
    fn the_seed_model_reads() {
        let model = seed_model();
        let graph = parse_model(&model).unwrap();
        assert_eq!(graph.nodes[0].op_type, "Conv");
        assert_eq!(graph.initializers[0].dims, [2, 1, 3, 3]);
        assert_eq!(graph.initializers[0].values().unwrap()[17], 17.0);
        assert_eq!(graph.initializers[1].values().unwrap(), [0.5, -0.5]);
    }

    #[test]
    fn dims_whose_product_overflows_are_an_error() {
        let init = Initializer {
            name: "w".into(),
            dims: vec![1 << 40, 1 << 40],
            data_type: 1,
            raw: Some(&[0; 8]),
            ..Initializer::default()
        };
        assert!(init.values().unwrap_err().contains("too large"));
    }

    /// Everything a weights file's bytes reach: the parse and every initializer's values.
    fn read_all(bytes: &[u8]) {
        if let Ok(graph) = parse_model(bytes) {
            for init in &graph.initializers {
                let _ = init.values();
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(crate::fuzz::cases()))]

        #[test]
        fn fuzz_random_bytes(bytes in crate::fuzz::random_bytes()) {
            crate::fuzz::within_allowance(&bytes, read_all);
        }

        #[test]
        fn fuzz_mutated_model(bytes in crate::fuzz::mutated(seed_model())) {
            crate::fuzz::within_allowance(&bytes, read_all);
        }
    }
}
