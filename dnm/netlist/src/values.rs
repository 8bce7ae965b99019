//! Turning a port's bytes into JSON for operators, using the message schema alone.
//!
//! Fixed-size messages are `repr(C)` structs whose `SCHEMA` lists their fields in ROS 2 `.msg`
//! syntax in layout order (see the module SDK's `msg`); this decodes primitive fields and fixed-size
//! arrays of them, honouring C alignment. Anything else is summarised by its size.

use serde_json::{Map, Value, json};

/// The JSON view of one sample of a port with this message type.
pub fn decode(message: &crate::MessageType, bytes: &[u8]) -> Value {
    if message.encoding == crate::POD_ENCODING
        && let Some(v) = decode_pod(&message.schema, bytes)
    {
        return v;
    }
    if message.encoding == "application/json"
        && let Ok(v) = serde_json::from_slice::<Value>(bytes)
    {
        return v;
    }
    json!({ "bytes": bytes.len() })
}

fn primitive(ty: &str) -> Option<usize> {
    Some(match ty {
        "bool" | "int8" | "uint8" | "byte" | "char" => 1,
        "int16" | "uint16" => 2,
        "int32" | "uint32" | "float32" => 4,
        "int64" | "uint64" | "float64" => 8,
        _ => return None,
    })
}

fn read(ty: &str, b: &[u8]) -> Value {
    macro_rules! le {
        ($t:ty) => {{
            let mut a = [0u8; size_of::<$t>()];
            a.copy_from_slice(b);
            <$t>::from_le_bytes(a)
        }};
    }
    match ty {
        "bool" => json!(b[0] != 0),
        "int8" => json!(b[0] as i8),
        "uint8" | "byte" | "char" => json!(b[0]),
        "int16" => json!(le!(i16)),
        "uint16" => json!(le!(u16)),
        "int32" => json!(le!(i32)),
        "uint32" => json!(le!(u32)),
        "float32" => json!(le!(f32)),
        "int64" => json!(le!(i64)),
        "uint64" => json!(le!(u64)),
        "float64" => json!(le!(f64)),
        _ => Value::Null,
    }
}

/// Decodes a `repr(C)` struct described by `.msg` lines; `None` if the schema has a field this
/// cannot lay out or the sizes disagree.
pub fn decode_pod(schema: &str, bytes: &[u8]) -> Option<Value> {
    let mut out = Map::new();
    let mut offset = 0usize;
    let mut max_align = 1usize;
    for line in schema.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (ty, name) = (parts.next()?, parts.next()?);
        let (base, count) = match ty.split_once('[') {
            Some((base, rest)) => (base, Some(rest.strip_suffix(']')?.parse::<usize>().ok()?)),
            None => (ty, None),
        };
        let size = primitive(base)?;
        max_align = max_align.max(size);
        offset = offset.next_multiple_of(size);
        let n = count.unwrap_or(1);
        // Counts come from a schema that may have crossed a network: no overflow.
        let end = offset.checked_add(size.checked_mul(n)?)?;
        let field = bytes.get(offset..end)?;
        let value = match count {
            None => read(base, field),
            Some(_) => Value::Array(field.chunks(size).map(|c| read(base, c)).collect()),
        };
        out.insert(name.to_string(), value);
        offset = end;
    }
    (offset.next_multiple_of(max_align) == bytes.len()).then_some(Value::Object(out))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{MessageType, Payload};

    #[test]
    fn decodes_messages_by_their_schema() {
        let tick = MessageType {
            schema_name: "dnm_msgs/Tick".into(),
            encoding: crate::POD_ENCODING.into(),
            schema: "uint64 origin\nuint64 seq\n".into(),
            payload: Payload::Fixed { size_bytes: 16 },
            standard: None,
        };
        let mut b = 3u64.to_le_bytes().to_vec();
        b.extend(9u64.to_le_bytes());
        assert_eq!(decode(&tick, &b), json!({"origin": 3, "seq": 9}));
        assert_eq!(decode(&tick, &b[..8]), json!({"bytes": 8}));
        let telemetry = MessageType {
            encoding: "application/json".into(),
            ..tick
        };
        assert_eq!(decode(&telemetry, b"{\"v\": 1}"), json!({"v": 1}));
    }

    #[test]
    fn honours_alignment_and_arrays() {
        // uint8 then float64: 7 bytes of padding; then float32[2] and final padding to 8.
        let mut b = vec![0u8; 32];
        b[0] = 1;
        b[8..16].copy_from_slice(&2.5f64.to_le_bytes());
        b[16..20].copy_from_slice(&1.0f32.to_le_bytes());
        b[20..24].copy_from_slice(&(-1.0f32).to_le_bytes());
        let v = decode_pod("uint8 flag\nfloat64 x\nfloat32[2] v\nint32 k\n", &b).unwrap();
        assert_eq!(v, json!({"flag": 1, "x": 2.5, "v": [1.0, -1.0], "k": 0}));
        assert!(decode_pod("float64 x\n", &b).is_none());
        assert!(decode_pod("string s\n", &b).is_none());
    }
}
