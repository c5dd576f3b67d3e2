//! CRC32C (Castagnoli), the checksum of every section and every tile.

/// CRC32C of `bytes`.
pub fn crc32c(bytes: &[u8]) -> u32 {
    crc32c::crc32c(bytes)
}

#[cfg(test)]
mod tests {
    #[test]
    fn matches_the_standard_check_value() {
        // RFC 3720 / iSCSI check value for "123456789".
        assert_eq!(super::crc32c(b"123456789"), 0xe306_9283);
    }
}
