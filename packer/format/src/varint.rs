//! LEB128 unsigned varints, as used by the directory encoding.

use crate::error::{Error, Result};

/// Appends `value` as an unsigned LEB128 varint.
#[expect(clippy::cast_possible_truncation, reason = "each byte is masked to 7 bits first")]
pub fn write_varint(out: &mut Vec<u8>, mut value: u64) {
    while value >= 0x80 {
        out.push(((value & 0x7f) as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

/// A cursor over untrusted bytes.
pub struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
    section: &'a str,
}

impl<'a> Cursor<'a> {
    /// A cursor at the start of `bytes`; `section` names them in errors.
    pub fn new(bytes: &'a [u8], section: &'a str) -> Self {
        Self { bytes, pos: 0, section }
    }

    /// Bytes not yet consumed.
    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// Reads one varint. A varint longer than 10 bytes or overflowing u64 is an error.
    ///
    /// # Errors
    /// [`Error::Corrupt`] on truncation or overflow.
    #[inline]
    pub fn varint(&mut self) -> Result<u64> {
        // Most directory varints are one byte (runs of 1, offsets that follow the previous
        // blob, small key steps).
        match self.bytes.get(self.pos) {
            Some(&byte) if byte < 0x80 => {
                self.pos += 1;
                Ok(u64::from(byte))
            }
            _ => self.varint_long(),
        }
    }

    fn varint_long(&mut self) -> Result<u64> {
        let mut value: u64 = 0;
        for shift in (0..64).step_by(7) {
            let Some(&byte) = self.bytes.get(self.pos) else {
                return Err(Error::corrupt(self.section, format!("truncated varint at byte {}", self.pos)));
            };
            self.pos += 1;
            let low = u64::from(byte & 0x7f);
            if shift == 63 && low > 1 {
                return Err(Error::corrupt(self.section, format!("varint overflows u64 at byte {}", self.pos - 1)));
            }
            value |= low << shift;
            if byte & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(Error::corrupt(self.section, format!("varint longer than 10 bytes at byte {}", self.pos)))
    }

    /// Reads a little-endian u32.
    ///
    /// # Errors
    /// [`Error::Corrupt`] on truncation.
    pub fn u32_le(&mut self) -> Result<u32> {
        let end = self.pos.checked_add(4).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(Error::corrupt(self.section, format!("truncated u32 at byte {}", self.pos)));
        };
        let mut b = [0u8; 4];
        b.copy_from_slice(&self.bytes[self.pos..end]);
        self.pos = end;
        Ok(u32::from_le_bytes(b))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_edge_values() {
        for v in [0, 1, 127, 128, 255, 300, 16_383, 16_384, u64::from(u32::MAX), u64::MAX - 1, u64::MAX] {
            let mut buf = Vec::new();
            write_varint(&mut buf, v);
            let mut c = Cursor::new(&buf, "test");
            assert_eq!(c.varint().unwrap(), v);
            assert_eq!(c.remaining(), 0);
        }
    }

    #[test]
    fn rejects_truncated_and_overlong() {
        assert!(Cursor::new(&[0x80], "t").varint().is_err());
        assert!(Cursor::new(&[0xff; 11], "t").varint().is_err());
        // 10th byte may only carry one bit.
        let mut over = vec![0xff; 9];
        over.push(0x02);
        assert!(Cursor::new(&over, "t").varint().is_err());
    }
}
