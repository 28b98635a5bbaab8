//! A cheap check that bytes are an ONNX model, without ONNX Runtime: the
//! protobuf wire format of an ONNX `ModelProto` (every field well formed to
//! the last byte, `ir_version` and `graph` present) and the names of its
//! graph's inputs and outputs. ONNX Runtime checks the rest when it loads
//! the model.

/// The names of an ONNX graph's inputs and outputs.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct GraphNames {
    /// Graph inputs (`GraphProto.input`), in order.
    pub inputs: Vec<String>,
    /// Graph outputs (`GraphProto.output`), in order.
    pub outputs: Vec<String>,
}

/// One protobuf field: its number and value.
enum Value<'a> {
    Varint(u64),
    Fixed,
    Bytes(&'a [u8]),
}

/// The fields of one protobuf message, or why it is not one.
fn fields(mut buf: &[u8]) -> Result<Vec<(u64, Value<'_>)>, String> {
    fn varint(buf: &mut &[u8]) -> Result<u64, String> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let (&b, rest) = buf.split_first().ok_or("truncated varint")?;
            *buf = rest;
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err("varint longer than 10 bytes".into())
    }
    let mut out = Vec::new();
    while !buf.is_empty() {
        let key = varint(&mut buf)?;
        let (field, wire) = (key >> 3, key & 7);
        if field == 0 {
            return Err("field number 0".into());
        }
        let value = match wire {
            0 => Value::Varint(varint(&mut buf)?),
            1 | 5 => {
                let n = if wire == 1 { 8 } else { 4 };
                if buf.len() < n {
                    return Err(format!("field {field}: truncated fixed-size value"));
                }
                buf = &buf[n..];
                Value::Fixed
            }
            2 => {
                let n = varint(&mut buf)?;
                let n = usize::try_from(n)
                    .ok()
                    .filter(|&n| n <= buf.len())
                    .ok_or_else(|| {
                        format!(
                            "field {field}: length {n} runs past the end ({} bytes left)",
                            buf.len()
                        )
                    })?;
                let (v, rest) = buf.split_at(n);
                buf = rest;
                Value::Bytes(v)
            }
            w => return Err(format!("field {field}: wire type {w} is not used by ONNX")),
        };
        out.push((field, value));
    }
    Ok(out)
}

/// Checks that `bytes` is an ONNX `ModelProto` and returns its graph's input
/// and output names; the error says what is wrong.
pub fn inspect(bytes: &[u8]) -> Result<GraphNames, String> {
    if bytes.is_empty() {
        return Err("it is empty".into());
    }
    let model = fields(bytes).map_err(|e| format!("not a protobuf message: {e}"))?;
    let mut ir_version = None;
    let mut graph = None;
    for (field, value) in &model {
        match (field, value) {
            (1, Value::Varint(v)) => ir_version = Some(*v),
            (7, Value::Bytes(g)) => graph = Some(*g),
            (1 | 5, _) => return Err(format!("ModelProto field {field} is not an integer")),
            (2..=4 | 6..=8 | 14, Value::Varint(_) | Value::Fixed) => {
                return Err(format!(
                    "ModelProto field {field} is not a message or string"
                ))
            }
            _ => {}
        }
    }
    match ir_version {
        None => return Err("no ir_version (ModelProto field 1)".into()),
        Some(0) => return Err("ir_version is 0".into()),
        Some(_) => {}
    }
    let graph = graph.ok_or("no graph (ModelProto field 7)")?;
    let graph = fields(graph).map_err(|e| format!("its graph is malformed: {}", e))?;
    let mut names = GraphNames::default();
    for (field, value) in &graph {
        let list = match field {
            11 => &mut names.inputs,
            12 => &mut names.outputs,
            _ => continue,
        };
        let Value::Bytes(info) = value else {
            return Err(format!("GraphProto field {field} is not a ValueInfoProto"));
        };
        let info =
            fields(info).map_err(|e| format!("a graph input or output is malformed: {}", e))?;
        let name = info
            .iter()
            .find_map(|(f, v)| match (f, v) {
                (1, Value::Bytes(n)) => Some(*n),
                _ => None,
            })
            .ok_or("a graph input or output has no name")?;
        let name = std::str::from_utf8(name)
            .map_err(|_| "a graph input or output name is not UTF-8".to_string())?;
        list.push(name.to_string());
    }
    if names.inputs.is_empty() || names.outputs.is_empty() {
        return Err(format!(
            "its graph has {} inputs and {} outputs",
            names.inputs.len(),
            names.outputs.len()
        ));
    }
    Ok(names)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A minimal ModelProto: ir_version 8, a graph with input "x" and output "y".
    fn model(input: &str, output: &str) -> Vec<u8> {
        let info = |name: &str| {
            let mut v = vec![0x0a, name.len() as u8];
            v.extend_from_slice(name.as_bytes());
            v
        };
        let mut graph = Vec::new();
        for (field, name) in [(11u8, input), (12, output)] {
            let i = info(name);
            graph.push(field << 3 | 2);
            graph.push(i.len() as u8);
            graph.extend(i);
        }
        let mut m = vec![0x08, 8, 0x3a, graph.len() as u8];
        m.extend(graph);
        m
    }

    #[test]
    fn reads_the_graph_names() {
        let names = inspect(&model("x", "y")).unwrap();
        assert_eq!(names.inputs, ["x"]);
        assert_eq!(names.outputs, ["y"]);
    }

    #[test]
    fn refuses_what_is_not_an_onnx_model() {
        for (bytes, want) in [
            (&b""[..], "empty"),
            (b"this is not an onnx model", "not a protobuf"),
            (b"{\"format_version\": 1}", "not a protobuf"),
            (&[0x08, 8][..], "no graph"),
            (&[0x3a, 0][..], "ir_version"),
            (&[0x08, 8, 0x3a, 9, 1][..], "runs past the end"),
        ] {
            let e = inspect(bytes).unwrap_err();
            assert!(e.contains(want), "{bytes:?}: {e}");
        }
        let mut cut = model("x", "y");
        cut.pop();
        assert!(inspect(&cut).is_err());
    }
}
