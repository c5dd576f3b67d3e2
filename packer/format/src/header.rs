//! The fixed 128-byte header at offset 0 (FORMAT.md §2).

use crate::checksum::crc32c;
use crate::error::{Error, Result};

/// Magic bytes: "TSPACK" followed by CR LF, which catches text-mode mangling.
pub const MAGIC: [u8; 8] = *b"TSPACK\r\n";
/// Size of the header in bytes.
pub const HEADER_LEN: usize = 128;
/// Newest major version this crate reads and writes; it reads every major from 1 up to
/// this one and writes the lowest that holds an archive's metadata
/// ([`crate::Metadata::format_major`]): 3 only where a layer is a water layer, 2 only
/// where a layer is `zstd_gradient`.
pub const VERSION_MAJOR: u16 = 3;
/// Minor version written by this crate; readers accept any minor of their major.
pub const VERSION_MINOR: u16 = 0;
/// What a reader fetches first when it knows nothing of the archive.
pub const BOOTSTRAP_READ: u64 = 16 * 1024;

/// How a directory or the metadata is compressed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    /// Stored as is.
    None,
    /// One zstd frame.
    Zstd,
}

impl Compression {
    fn to_byte(self) -> u8 {
        match self {
            Self::None => 1,
            Self::Zstd => 2,
        }
    }

    fn from_byte(b: u8, field: &str) -> Result<Self> {
        match b {
            1 => Ok(Self::None),
            2 => Ok(Self::Zstd),
            other => Err(Error::corrupt("header", format!("unknown {field} compression {other}"))),
        }
    }
}

/// A byte range of the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Section {
    /// Absolute offset in the file.
    pub offset: u64,
    /// Length in bytes.
    pub len: u64,
}

impl Section {
    /// One past the last byte; `None` if that overflows u64.
    pub fn end(self) -> Option<u64> {
        self.offset.checked_add(self.len)
    }
}

/// The decoded header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Header {
    /// Major version of the file (1..=[`VERSION_MAJOR`]).
    pub version_major: u16,
    /// Minor version of the file.
    pub version_minor: u16,
    /// Metadata JSON.
    pub metadata: Section,
    /// Root directory.
    pub root_dir: Section,
    /// All leaf directories, back to back.
    pub leaf_dirs: Section,
    /// All tile blobs (payload + CRC32C trailer), coarse LODs first.
    pub data: Section,
    /// Tiles addressed by the directories (runs expanded).
    pub addressed_tiles: u64,
    /// Directory entries that point at tile data.
    pub tile_entries: u64,
    /// Distinct tile blobs stored.
    pub tile_contents: u64,
    /// CRC32C of the stored metadata bytes.
    pub metadata_crc: u32,
    /// CRC32C of the stored root directory bytes.
    pub root_dir_crc: u32,
    /// Compression of the metadata.
    pub metadata_compression: Compression,
    /// Compression of the root and leaf directories.
    pub directory_compression: Compression,
}

impl Header {
    /// Bytes to read at offset 0 to hold header, metadata and root directory.
    pub fn bootstrap_len(&self) -> u64 {
        self.root_dir.offset.saturating_add(self.root_dir.len)
    }

    /// Serializes to the 128-byte on-disk form.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[0..8].copy_from_slice(&MAGIC);
        b[8..10].copy_from_slice(&self.version_major.to_le_bytes());
        b[10..12].copy_from_slice(&self.version_minor.to_le_bytes());
        b[12..16].copy_from_slice(&128u32.to_le_bytes());
        let u64s = [
            self.bootstrap_len(),
            self.metadata.offset,
            self.metadata.len,
            self.root_dir.offset,
            self.root_dir.len,
            self.leaf_dirs.offset,
            self.leaf_dirs.len,
            self.data.offset,
            self.data.len,
            self.addressed_tiles,
            self.tile_entries,
            self.tile_contents,
        ];
        for (i, v) in u64s.iter().enumerate() {
            let at = 16 + 8 * i;
            b[at..at + 8].copy_from_slice(&v.to_le_bytes());
        }
        b[112..116].copy_from_slice(&self.metadata_crc.to_le_bytes());
        b[116..120].copy_from_slice(&self.root_dir_crc.to_le_bytes());
        b[120] = self.metadata_compression.to_byte();
        b[121] = self.directory_compression.to_byte();
        // 122..124 reserved, zero.
        let crc = crc32c(&b[..124]);
        b[124..128].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses and validates a header against the file's length.
    ///
    /// # Errors
    /// [`Error::BadMagic`], [`Error::UnsupportedVersion`], [`Error::SectionChecksum`] for a
    /// damaged header, [`Error::Corrupt`] / [`Error::OutOfBounds`] for inconsistent sections.
    pub fn decode(bytes: &[u8], file_len: u64) -> Result<Self> {
        if bytes.len() < 16 || bytes[0..8] != MAGIC {
            return Err(Error::BadMagic);
        }
        let u16_at = |at: usize| u16::from_le_bytes([bytes[at], bytes[at + 1]]);
        let (major, minor) = (u16_at(8), u16_at(10));
        if !(1..=VERSION_MAJOR).contains(&major) {
            return Err(Error::UnsupportedVersion { major, minor });
        }
        if bytes.len() < HEADER_LEN {
            return Err(Error::corrupt("header", format!("truncated: {} of {HEADER_LEN} bytes", bytes.len())));
        }
        let b = &bytes[..HEADER_LEN];
        let u32_at = |at: usize| u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]);
        let u64_at = |at: usize| {
            let mut a = [0u8; 8];
            a.copy_from_slice(&b[at..at + 8]);
            u64::from_le_bytes(a)
        };
        let stored = u32_at(124);
        let computed = crc32c(&b[..124]);
        if stored != computed {
            return Err(Error::SectionChecksum { section: "header".into(), stored, computed });
        }
        let header_len = u32_at(12);
        if header_len as usize != HEADER_LEN {
            return Err(Error::corrupt("header", format!("header length {header_len}, expected {HEADER_LEN}")));
        }
        let section = |at: usize| Section { offset: u64_at(at), len: u64_at(at + 8) };
        let header = Self {
            version_major: major,
            version_minor: minor,
            metadata: section(24),
            root_dir: section(40),
            leaf_dirs: section(56),
            data: section(72),
            addressed_tiles: u64_at(88),
            tile_entries: u64_at(96),
            tile_contents: u64_at(104),
            metadata_crc: u32_at(112),
            root_dir_crc: u32_at(116),
            metadata_compression: Compression::from_byte(b[120], "metadata")?,
            directory_compression: Compression::from_byte(b[121], "directory")?,
        };
        let bootstrap = u64_at(16);
        if bootstrap != header.bootstrap_len() {
            return Err(Error::corrupt(
                "header",
                format!("bootstrap length {bootstrap} != root directory end {}", header.bootstrap_len()),
            ));
        }
        header.validate_layout(file_len)?;
        Ok(header)
    }

    /// Sections must follow one another in order without overlap and end inside the file.
    fn validate_layout(&self, file_len: u64) -> Result<()> {
        let sections = [
            ("metadata", self.metadata),
            ("root directory", self.root_dir),
            ("leaf directories", self.leaf_dirs),
            ("data section", self.data),
        ];
        let mut previous_end = HEADER_LEN as u64;
        for (name, s) in sections {
            let Some(end) = s.end().filter(|&e| e <= file_len) else {
                return Err(Error::OutOfBounds {
                    what: name.to_owned(),
                    offset: s.offset,
                    len: s.len,
                    limit_name: "file",
                    limit: file_len,
                });
            };
            if s.offset < previous_end {
                return Err(Error::corrupt("header", format!("{name} at {} overlaps the previous section", s.offset)));
            }
            previous_end = end;
        }
        if self.root_dir.len == 0 {
            return Err(Error::corrupt("header", "empty root directory"));
        }
        if self.tile_contents > self.tile_entries || self.tile_entries > self.addressed_tiles {
            return Err(Error::corrupt("header", "tile counts are inconsistent"));
        }
        // Every stored blob holds at least one payload byte and a 4-byte checksum.
        if self.tile_contents > self.data.len / 5 {
            return Err(Error::corrupt("header", "more tile contents than the data section can hold"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Header {
        Header {
            version_major: 1,
            version_minor: 0,
            metadata: Section { offset: 128, len: 300 },
            root_dir: Section { offset: 428, len: 50 },
            leaf_dirs: Section { offset: 478, len: 0 },
            data: Section { offset: 478, len: 5 << 32 },
            addressed_tiles: 12,
            tile_entries: 10,
            tile_contents: 9,
            metadata_crc: 7,
            root_dir_crc: 8,
            metadata_compression: Compression::Zstd,
            directory_compression: Compression::Zstd,
        }
    }

    #[test]
    fn write_then_read() {
        let h = sample();
        let file_len = h.data.end().unwrap();
        assert_eq!(Header::decode(&h.encode(), file_len).unwrap(), h);
    }

    /// Majors 1 to 3 are read (2 only adds a payload compression, 3 a layer kind); 0 and
    /// 4 are refused before anything else is looked at.
    #[test]
    fn reads_majors_one_to_three_only() {
        let mut h = sample();
        let file_len = h.data.end().unwrap();
        for major in [2, 3] {
            h.version_major = major;
            assert_eq!(Header::decode(&h.encode(), file_len).unwrap(), h);
        }
        for major in [0, 4, 0x8001] {
            h.version_major = major;
            let err = Header::decode(&h.encode(), file_len).unwrap_err();
            assert!(matches!(err, Error::UnsupportedVersion { major: m, minor: 0 } if m == major), "{err}");
        }
    }

    #[test]
    fn every_single_bit_flip_is_detected() {
        let h = sample();
        let file_len = h.data.end().unwrap();
        let good = h.encode();
        for bit in 0..HEADER_LEN * 8 {
            let mut bad = good;
            bad[bit / 8] ^= 1 << (bit % 8);
            assert!(Header::decode(&bad, file_len).is_err(), "bit {bit} flip went unnoticed");
        }
    }

    #[test]
    fn rejects_sections_past_the_end_of_file() {
        let h = sample();
        let err = Header::decode(&h.encode(), h.data.end().unwrap() - 1).unwrap_err();
        assert!(matches!(err, Error::OutOfBounds { .. }), "{err}");
    }

    #[test]
    fn rejects_other_files() {
        assert!(matches!(Header::decode(b"\x89PNG\r\n\x1a\n", 100), Err(Error::BadMagic)));
        assert!(matches!(Header::decode(b"", 0), Err(Error::BadMagic)));
    }
}
