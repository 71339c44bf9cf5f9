//! The Foxglove well-known types shoal writes, their schema records and
//! their encoding: one place for both the log and the live server.

use foxglove::messages as fm;
use foxglove::{Encode, Schema};

/// A Foxglove well-known schema shoal writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum FoxgloveSchema {
    FrameTransforms,
    PosesInFrame,
    Log,
    SceneUpdate,
    CompressedImage,
    ImageAnnotations,
}

/// `T`'s schema record as the `foxglove` crate ships it (a protobuf
/// `FileDescriptorSet` of Foxglove's published `.proto` files).
fn schema_of<T: Encode>(name: &'static str) -> Schema {
    // The well-known types always carry their schema; an empty one would
    // still be a valid record (readers then show raw bytes).
    T::get_schema().unwrap_or_else(|| Schema::new(name, "protobuf", Vec::new()))
}

impl FoxgloveSchema {
    pub const ALL: [FoxgloveSchema; 6] = [
        FoxgloveSchema::FrameTransforms,
        FoxgloveSchema::PosesInFrame,
        FoxgloveSchema::Log,
        FoxgloveSchema::SceneUpdate,
        FoxgloveSchema::CompressedImage,
        FoxgloveSchema::ImageAnnotations,
    ];

    /// Schema name as Foxglove knows it.
    pub fn name(self) -> &'static str {
        match self {
            FoxgloveSchema::FrameTransforms => "foxglove.FrameTransforms",
            FoxgloveSchema::PosesInFrame => "foxglove.PosesInFrame",
            FoxgloveSchema::Log => "foxglove.Log",
            FoxgloveSchema::SceneUpdate => "foxglove.SceneUpdate",
            FoxgloveSchema::CompressedImage => "foxglove.CompressedImage",
            FoxgloveSchema::ImageAnnotations => "foxglove.ImageAnnotations",
        }
    }

    /// The schema record (name, encoding `protobuf`, descriptor bytes) the
    /// log and the live server both declare.
    pub fn schema(self) -> Schema {
        let name = self.name();
        match self {
            FoxgloveSchema::FrameTransforms => schema_of::<fm::FrameTransforms>(name),
            FoxgloveSchema::PosesInFrame => schema_of::<fm::PosesInFrame>(name),
            FoxgloveSchema::Log => schema_of::<fm::Log>(name),
            FoxgloveSchema::SceneUpdate => schema_of::<fm::SceneUpdate>(name),
            FoxgloveSchema::CompressedImage => schema_of::<fm::CompressedImage>(name),
            FoxgloveSchema::ImageAnnotations => schema_of::<fm::ImageAnnotations>(name),
        }
    }

    /// The channels' message encoding.
    pub fn message_encoding(self) -> &'static str {
        MESSAGE_ENCODING
    }
}

/// Message encoding of every Foxglove channel shoal writes.
pub const MESSAGE_ENCODING: &str = "protobuf";

/// One Foxglove message, typed.
#[derive(Debug, Clone, PartialEq)]
pub enum FoxgloveValue {
    FrameTransforms(fm::FrameTransforms),
    PosesInFrame(fm::PosesInFrame),
    Log(fm::Log),
    SceneUpdate(fm::SceneUpdate),
    CompressedImage(fm::CompressedImage),
    ImageAnnotations(fm::ImageAnnotations),
}

/// Protobuf-encode `m` into a buffer sized by its encoded length.
fn encode_one<T: Encode>(m: &T) -> Result<Vec<u8>, String> {
    let mut buf = Vec::with_capacity(m.encoded_len().unwrap_or(256));
    m.encode(&mut buf).map_err(|e| e.to_string())?;
    Ok(buf)
}

impl FoxgloveValue {
    pub fn schema(&self) -> FoxgloveSchema {
        match self {
            FoxgloveValue::FrameTransforms(_) => FoxgloveSchema::FrameTransforms,
            FoxgloveValue::PosesInFrame(_) => FoxgloveSchema::PosesInFrame,
            FoxgloveValue::Log(_) => FoxgloveSchema::Log,
            FoxgloveValue::SceneUpdate(_) => FoxgloveSchema::SceneUpdate,
            FoxgloveValue::CompressedImage(_) => FoxgloveSchema::CompressedImage,
            FoxgloveValue::ImageAnnotations(_) => FoxgloveSchema::ImageAnnotations,
        }
    }

    /// The protobuf bytes (a `Vec` grows as needed, so this fails only on a
    /// bug in the encoder; the error text says what prost reported).
    pub fn encode(&self) -> Result<Vec<u8>, String> {
        match self {
            FoxgloveValue::FrameTransforms(m) => encode_one(m),
            FoxgloveValue::PosesInFrame(m) => encode_one(m),
            FoxgloveValue::Log(m) => encode_one(m),
            FoxgloveValue::SceneUpdate(m) => encode_one(m),
            FoxgloveValue::CompressedImage(m) => encode_one(m),
            FoxgloveValue::ImageAnnotations(m) => encode_one(m),
        }
    }
}

/// One Foxglove message on its topic.
#[derive(Debug, Clone, PartialEq)]
pub struct FoxgloveMessage {
    pub topic: String,
    pub value: FoxgloveValue,
}

impl FoxgloveMessage {
    pub fn schema(&self) -> FoxgloveSchema {
        self.value.schema()
    }

    /// The message's bytes on its channel (log and live alike).
    pub fn encode(&self) -> Result<Vec<u8>, crate::RecordError> {
        self.value
            .encode()
            .map_err(|reason| crate::RecordError::FoxgloveEncode {
                topic: self.topic.clone(),
                reason,
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_schema_is_the_crates_protobuf_descriptor_under_its_name() {
        for s in FoxgloveSchema::ALL {
            let sc = s.schema();
            assert_eq!(sc.name, s.name());
            assert_eq!(sc.encoding, "protobuf");
            // A FileDescriptorSet naming the type's .proto file.
            let file = format!("foxglove/{}.proto", &s.name()["foxglove.".len()..]);
            assert!(
                sc.data.windows(file.len()).any(|w| w == file.as_bytes()),
                "{}: descriptor does not name {file}",
                s.name()
            );
        }
    }

    #[test]
    fn a_log_line_round_trips_through_protobuf() {
        let m = fm::Log {
            timestamp: Some(fm::Timestamp::new(12, 345)),
            level: fm::log::Level::Warning as i32,
            message: "node 10 up".into(),
            name: "node/10".into(),
            file: String::new(),
            line: 0,
        };
        let bytes = FoxgloveValue::Log(m.clone()).encode().unwrap();
        let back = <fm::Log as foxglove::Decode>::decode(&bytes[..]).unwrap();
        assert_eq!(back, m);
    }
}
