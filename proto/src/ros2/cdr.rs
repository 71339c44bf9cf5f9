//! OMG CDR (XCDR1, "plain CDR"), the serialization ROS 2 puts on the wire and
//! in `ros2` MCAP/bag files: a 4-byte encapsulation header (`00 01 00 00`
//! little-endian, `00 00 00 00` big-endian), then every primitive aligned to
//! its own size counted from the byte after the header; strings are a `u32`
//! length including the NUL, the bytes, the NUL; sequences a `u32` count then
//! the elements.
//!
//! [`CdrWriter`] writes little-endian (what every ROS 2 middleware on
//! x86/ARM emits); [`CdrReader`] reads either byte order and never reads past
//! the end: a length that does not fit is an error naming the field.

/// Encapsulation header of little-endian plain CDR.
pub const ENCAPSULATION_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];
/// Encapsulation header of big-endian plain CDR.
pub const ENCAPSULATION_BE: [u8; 4] = [0x00, 0x00, 0x00, 0x00];

/// Why bytes are not the CDR message expected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CdrError {
    #[error("CDR: {0} bytes is too short for the encapsulation header")]
    NoHeader(usize),
    #[error("CDR: encapsulation {0:02x?} is not plain CDR (00 00 / 00 01)")]
    Encapsulation([u8; 2]),
    #[error("CDR: {field} at byte {at} needs {need} bytes, {left} left")]
    Truncated {
        field: &'static str,
        at: usize,
        need: usize,
        left: usize,
    },
    #[error("CDR: {field} at byte {at}: {reason}")]
    Invalid {
        field: &'static str,
        at: usize,
        reason: String,
    },
}

/// Little-endian plain-CDR writer.
#[derive(Debug, Clone)]
pub struct CdrWriter {
    buf: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    pub fn new() -> Self {
        let mut buf = Vec::with_capacity(256);
        buf.extend_from_slice(&ENCAPSULATION_LE);
        Self { buf }
    }

    /// Pad with zeros to a multiple of `n` (counted after the header).
    fn align(&mut self, n: usize) {
        let offset = self.buf.len() - ENCAPSULATION_LE.len();
        let pad = (n - offset % n) % n;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    /// A `string`: length with the NUL, bytes, NUL. (A ROS string holds no NUL.)
    pub fn string(&mut self, s: &str) {
        let bytes = s.as_bytes();
        let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
        self.u32(end as u32 + 1);
        self.buf.extend_from_slice(&bytes[..end]);
        self.buf.push(0);
    }
    /// The element count of a sequence that follows.
    pub fn sequence_len(&mut self, n: usize) {
        self.u32(n as u32);
    }
    /// A `sequence<uint8>`.
    pub fn bytes(&mut self, data: &[u8]) {
        self.sequence_len(data.len());
        self.buf.extend_from_slice(data);
    }

    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// Plain-CDR reader of either byte order.
#[derive(Debug, Clone)]
pub struct CdrReader<'a> {
    data: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> CdrReader<'a> {
    /// Check the encapsulation header and position after it.
    pub fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        if data.len() < 4 {
            return Err(CdrError::NoHeader(data.len()));
        }
        let little = match [data[0], data[1]] {
            [0x00, 0x01] => true,
            [0x00, 0x00] => false,
            other => return Err(CdrError::Encapsulation(other)),
        };
        Ok(Self {
            data,
            pos: 4,
            little,
        })
    }

    fn take(&mut self, field: &'static str, n: usize) -> Result<&'a [u8], CdrError> {
        let left = self.data.len() - self.pos;
        if n > left {
            return Err(CdrError::Truncated {
                field,
                at: self.pos,
                need: n,
                left,
            });
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn align(&mut self, field: &'static str, n: usize) -> Result<(), CdrError> {
        let offset = self.pos - 4;
        let pad = (n - offset % n) % n;
        self.take(field, pad).map(|_| ())
    }

    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], CdrError> {
        self.align(field, N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(field, N)?);
        if !self.little {
            a.reverse();
        }
        Ok(a)
    }

    pub fn u8(&mut self, field: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(field, 1)?[0])
    }
    pub fn u32(&mut self, field: &'static str) -> Result<u32, CdrError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }
    pub fn i32(&mut self, field: &'static str) -> Result<i32, CdrError> {
        Ok(i32::from_le_bytes(self.array(field)?))
    }
    pub fn f64(&mut self, field: &'static str) -> Result<f64, CdrError> {
        Ok(f64::from_le_bytes(self.array(field)?))
    }

    /// A sequence's element count, refused when even `min_element_bytes`
    /// per element could not fit in what is left (no huge allocations from
    /// a corrupt count).
    pub fn sequence_len(
        &mut self,
        field: &'static str,
        min_element_bytes: usize,
    ) -> Result<usize, CdrError> {
        let at = self.pos;
        let n = self.u32(field)? as usize;
        let left = self.data.len() - self.pos;
        if n.saturating_mul(min_element_bytes.max(1)) > left {
            return Err(CdrError::Invalid {
                field,
                at,
                reason: format!("{n} elements cannot fit in the {left} bytes left"),
            });
        }
        Ok(n)
    }

    pub fn string(&mut self, field: &'static str) -> Result<String, CdrError> {
        let at = self.pos;
        let n = self.sequence_len(field, 1)?;
        let bytes = self.take(field, n)?;
        let text = match bytes.split_last() {
            Some((0, text)) => text,
            // Some writers leave out the NUL of an empty string.
            None => &[][..],
            Some(_) => {
                return Err(CdrError::Invalid {
                    field,
                    at,
                    reason: "string not NUL-terminated".into(),
                })
            }
        };
        String::from_utf8(text.to_vec()).map_err(|e| CdrError::Invalid {
            field,
            at,
            reason: format!("not UTF-8: {e}"),
        })
    }

    /// A `sequence<uint8>`, borrowed.
    pub fn bytes(&mut self, field: &'static str) -> Result<&'a [u8], CdrError> {
        let n = self.sequence_len(field, 1)?;
        self.take(field, n)
    }

    /// Bytes not read (trailing padding of a message is allowed).
    pub fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_counts_from_after_the_header() {
        let mut w = CdrWriter::new();
        w.u8(7);
        w.f64(1.5);
        w.string("ab");
        w.u32(9);
        let b = w.finish();
        // header 4, u8 at 4, pad to 8 after header (offset 8 -> byte 12), f64 12..20,
        // string len at 20..24, "ab\0" 24..27, pad to 28, u32 28..32.
        assert_eq!(&b[..4], &ENCAPSULATION_LE);
        assert_eq!(b[4], 7);
        assert_eq!(&b[5..12], &[0; 7]);
        assert_eq!(f64::from_le_bytes(b[12..20].try_into().unwrap()), 1.5);
        assert_eq!(u32::from_le_bytes(b[20..24].try_into().unwrap()), 3);
        assert_eq!(&b[24..27], b"ab\0");
        assert_eq!(u32::from_le_bytes(b[28..32].try_into().unwrap()), 9);
        assert_eq!(b.len(), 32);
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.u8("a").unwrap(), 7);
        assert_eq!(r.f64("b").unwrap(), 1.5);
        assert_eq!(r.string("c").unwrap(), "ab");
        assert_eq!(r.u32("d").unwrap(), 9);
        assert_eq!(r.remaining(), 0);
    }

    #[test]
    fn big_endian_reads_and_bad_input_is_named() {
        let be = [0u8, 0, 0, 0, 0, 0, 0, 5, 0xAA];
        let mut r = CdrReader::new(&be).unwrap();
        assert_eq!(r.u32("n").unwrap(), 5);
        assert!(matches!(
            r.u32("m"),
            Err(CdrError::Truncated { field: "m", .. })
        ));
        assert_eq!(CdrReader::new(&[0, 1]).unwrap_err(), CdrError::NoHeader(2));
        assert!(matches!(
            CdrReader::new(&[0, 7, 0, 0]),
            Err(CdrError::Encapsulation(_))
        ));
        // A count of 4 billion elements is refused before any allocation.
        let mut w = CdrWriter::new();
        w.u32(u32::MAX);
        let b = w.finish();
        let err = CdrReader::new(&b).unwrap().bytes("data").unwrap_err();
        assert!(err.to_string().contains("data"), "{err}");
    }
}
