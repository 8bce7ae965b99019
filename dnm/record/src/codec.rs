//! A port sample as a recording stores it, and back: the message a sample becomes on its
//! channel ([`encode`], under the schema [`mcap_encoding`] gives), and the port's bytes again
//! from a recorded message ([`decode`]; a standard message is read back through its
//! [`StandardMapping`]).

use std::sync::Arc;

use dnm_netlist::{MessageType, Payload};

pub use crate::standard::DecodeError;
use crate::standard::{Cdr, StandardMapping};

/// Why a recorded message did not become a sample of its port.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReadError {
    #[error(transparent)]
    Decode(#[from] DecodeError),
    /// The bytes decoded, but not to a sample the port's type allows (the recorded netlist
    /// gives another type than the one recorded).
    #[error("{len} bytes do not fit {message}")]
    DoesNotFit { len: usize, message: String },
}

/// Schema (name, encoding, text) and message encoding of a port in the file.
pub fn mcap_encoding(message: &MessageType) -> (String, &'static str, String, &'static str) {
    if message.encoding == dnm_module::msg::POD_ENCODING {
        (
            message.schema_name.clone(),
            "ros2msg",
            message.schema.clone(),
            "cdr",
        )
    } else if message.encoding == "dnm-image-rgb8" {
        (
            "sensor_msgs/msg/Image".into(),
            "ros2msg",
            IMAGE_SCHEMA.into(),
            "cdr",
        )
    } else if message.encoding == "application/json" {
        (
            message.schema_name.clone(),
            "jsonschema",
            message.schema.clone(),
            "json",
        )
    } else {
        (
            message.schema_name.clone(),
            "ros2msg",
            "uint8[] data\n".into(),
            "cdr",
        )
    }
}

/// `sensor_msgs/msg/Image` with its dependencies, as ROS 2 tools expect a schema.
const IMAGE_SCHEMA: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";

/// The bytes a port sample is stored as.
pub fn encode(message: &MessageType, frame: &str, stamp_unix_ns: u64, bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    encode_into(&mut out, message, frame, stamp_unix_ns, bytes);
    out
}

/// [`encode`] into `out`, reusing its memory.
pub fn encode_into(
    out: &mut Vec<u8>,
    message: &MessageType,
    frame: &str,
    stamp_unix_ns: u64,
    bytes: &[u8],
) {
    if message.encoding == "application/json" {
        out.clear();
        out.extend_from_slice(bytes);
        return;
    }
    let mut c = Cdr::reuse(std::mem::take(out), bytes.len());
    if message.encoding == dnm_module::msg::POD_ENCODING {
        c.0.extend_from_slice(bytes);
    } else if message.encoding == "dnm-image-rgb8" && bytes.len() >= 12 {
        let word =
            |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
        let (width, height, step) = (word(0), word(4), word(8));
        c.i32((stamp_unix_ns / 1_000_000_000) as i32);
        c.u32((stamp_unix_ns % 1_000_000_000) as u32);
        c.string(frame);
        c.u32(height);
        c.u32(width);
        c.string("rgb8");
        c.0.push(0); // is_bigendian
        c.u32(step);
        c.bytes(&bytes[12..]);
    } else {
        c.bytes(bytes);
    }
    *out = c.0;
}

/// The port bytes a recorded message in the port's own type came from (the inverse of
/// [`encode`]).
pub fn decode(message: &MessageType, data: &[u8]) -> Result<Vec<u8>, DecodeError> {
    if message.encoding == dnm_module::msg::POD_ENCODING {
        data.get(4..)
            .map(<[u8]>::to_vec)
            .ok_or(DecodeError::ShortHeader)
    } else if message.encoding == "application/json" {
        Ok(data.to_vec())
    } else if message.encoding == "dnm-image-rgb8" {
        image(data)
    } else {
        let len = data
            .get(4..8)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
            .ok_or(DecodeError::ShortHeader)?;
        data.get(8..8usize.saturating_add(len))
            .map(<[u8]>::to_vec)
            .ok_or(DecodeError::SequencePastEnd)
    }
}

/// A camera frame (12-byte header: width, height, step; then the rows) from the
/// `sensor_msgs/msg/Image` the recorder wrote.
fn image(data: &[u8]) -> Result<Vec<u8>, DecodeError> {
    let mut at = 4usize;
    let mut take = |align: usize, n: usize| -> Result<&[u8], DecodeError> {
        while !(at - 4).is_multiple_of(align) {
            at += 1;
        }
        let s = data
            .get(at..at.saturating_add(n))
            .ok_or(DecodeError::ImageEndsEarly)?;
        at += n;
        Ok(s)
    };
    let u32_of = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    if data.get(..2) != Some(&[0, 1]) {
        return Err(DecodeError::NotLittleEndian);
    }
    take(4, 8)?; // stamp
    let n = u32_of(take(4, 4)?) as usize;
    take(1, n)?; // frame id
    let height = u32_of(take(4, 4)?);
    let width = u32_of(take(4, 4)?);
    let n = u32_of(take(4, 4)?) as usize;
    let encoding = take(1, n)?;
    if encoding != b"rgb8\0" {
        return Err(DecodeError::NotRgb8 {
            encoding: String::from_utf8_lossy(encoding).into_owned(),
        });
    }
    take(1, 1)?; // is_bigendian
    let step = u32_of(take(4, 4)?);
    let n = u32_of(take(4, 4)?) as usize;
    let pixels = take(1, n)?;
    let mut out = Vec::with_capacity(12 + pixels.len());
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    out.extend_from_slice(&step.to_le_bytes());
    out.extend_from_slice(pixels);
    Ok(out)
}

/// How a channel's messages become its port's bytes.
#[derive(Clone)]
pub(crate) enum Reading {
    Own,
    Standard(Arc<StandardMapping>),
}

/// How a message recorded as `schema` on a channel of `message`'s port becomes the port's
/// bytes (`raw`: the channel of its own bytes kept beside a standard message).
pub(crate) fn reading_of(
    message: &MessageType,
    schema: &str,
    raw: bool,
) -> Result<Reading, String> {
    let own = raw
        || schema == message.schema_name
        || (message.encoding == "dnm-image-rgb8" && schema == "sensor_msgs/msg/Image");
    if own {
        return Ok(Reading::Own);
    }
    match StandardMapping::of(message) {
        Ok(Some(mapping)) if mapping.name() == schema => Ok(Reading::Standard(Arc::new(mapping))),
        _ => Err(format!(
            "recorded as {schema}, which {} cannot be read back from",
            message.schema_name
        )),
    }
}

impl Reading {
    /// The port's bytes from a recorded message.
    pub(crate) fn read(&self, message: &MessageType, data: &[u8]) -> Result<Vec<u8>, ReadError> {
        let p = match self {
            Reading::Own => decode(message, data)?,
            Reading::Standard(mapping) => mapping.decode(data)?,
        };
        let fits = match message.payload {
            Payload::Fixed { size_bytes } => p.len() == size_bytes,
            Payload::Bytes { max_bytes } => p.len() <= max_bytes,
        };
        if fits {
            Ok(p)
        } else {
            Err(ReadError::DoesNotFit {
                len: p.len(),
                message: message.to_string(),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dnm_module::msg::{BytesMessage, Message, Tick};

    struct Frame;
    impl BytesMessage for Frame {
        const SCHEMA_NAME: &'static str = "test/Frame";
        const ENCODING: &'static str = "application/octet-stream";
        const SCHEMA: &'static str = "uint8[] data";
    }

    /// One message of each encoding the recorder writes: raw bytes, an RGB8 image (2×4 pixels),
    /// a fixed-size message, JSON.
    fn samples() -> Vec<(MessageType, Vec<u8>)> {
        let mut image = vec![9u8; 12 + 2 * 3 * 4];
        image[..12].copy_from_slice(&[4, 0, 0, 0, 2, 0, 0, 0, 12, 0, 0, 0]);
        let image_type = MessageType {
            encoding: "dnm-image-rgb8".into(),
            ..Frame::message_type(image.len())
        };
        let json_type = MessageType {
            encoding: "application/json".into(),
            ..Frame::message_type(64)
        };
        vec![
            (Frame::message_type(100), vec![7u8; 100]),
            (image_type, image),
            (Tick::message_type(), vec![1u8; 16]),
            (json_type, br#"{"a":1}"#.to_vec()),
        ]
    }

    #[test]
    fn decode_reads_back_what_encode_wrote() {
        for (message, bytes) in samples() {
            let stored = encode(&message, "cam", 1_700_000_000_123_456_789, &bytes);
            assert_eq!(decode(&message, &stored), Ok(bytes), "{}", message.encoding);
        }
    }

    #[test]
    fn a_reused_buffer_encodes_like_a_new_one() {
        // A buffer that held a longer message before.
        let mut buf = vec![0xee; 4096];
        for (message, bytes) in samples() {
            encode_into(&mut buf, &message, "cam", 1_700_000_000_123_456_789, &bytes);
            assert_eq!(
                buf,
                encode(&message, "cam", 1_700_000_000_123_456_789, &bytes),
                "{}",
                message.encoding
            );
        }
    }

    #[test]
    fn damaged_messages_say_what_is_wrong() {
        let bytes = Frame::message_type(100);
        assert_eq!(decode(&bytes, &[0, 1]), Err(DecodeError::ShortHeader));
        assert_eq!(
            decode(&bytes, &[0, 1, 0, 0, 9, 0, 0, 0, 1]),
            Err(DecodeError::SequencePastEnd)
        );
        let image = MessageType {
            encoding: "dnm-image-rgb8".into(),
            ..Frame::message_type(64)
        };
        assert_eq!(
            decode(&image, &[1, 0, 0, 0]),
            Err(DecodeError::NotLittleEndian)
        );
        assert_eq!(
            decode(&image, &[0, 1, 0, 0]),
            Err(DecodeError::ImageEndsEarly)
        );
        let mut bgr = encode(
            &image,
            "",
            0,
            &[1, 0, 0, 0, 1, 0, 0, 0, 3, 0, 0, 0, 1, 2, 3],
        );
        let at = bgr.windows(4).position(|w| w == b"rgb8").unwrap();
        bgr[at..at + 4].copy_from_slice(b"bgr8");
        assert_eq!(
            decode(&image, &bgr).unwrap_err().to_string(),
            "image encoding bgr8\0 is not rgb8"
        );
    }

    #[test]
    fn a_sample_that_does_not_fit_its_port_is_refused() {
        let tick = Tick::message_type();
        let stored = encode(&tick, "m", 0, &[0u8; 8]);
        let e = Reading::Own.read(&tick, &stored).unwrap_err();
        assert!(matches!(e, ReadError::DoesNotFit { len: 8, .. }), "{e}");
        assert!(e.to_string().starts_with("8 bytes do not fit "), "{e}");
    }
}
