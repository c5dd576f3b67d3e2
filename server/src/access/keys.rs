//! API keys: each allowed some archives (names or globs), optionally some HTTP origins, an
//! expiry and a rate. Kept in a TOML file as hashes (SHA-256), never in plain text: a key
//! is shown once, when it is made.
//!
//! A key reads `tk_{id}_{secret}`: `id` 8 hexadecimal digits that name the key (in the
//! file, in `key list`, nowhere else), `secret` 64 more from the system's random source.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use ring::digest;
use ring::rand::{SecureRandom, SystemRandom};
use serde::{Deserialize, Serialize};

use super::token::{hex, unhex};

/// One key's record in the keys file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyRecord {
    /// The key's name: the hexadecimal digits after `tk_`.
    pub id: String,
    /// SHA-256 of the whole key, hexadecimal.
    pub hash: String,
    /// Archive names or globs (`*` any run of characters, `?` one) it opens.
    pub archives: Vec<String>,
    /// HTTP origins (`https://maps.example.com`) it may be used from; empty: any.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub origins: Vec<String>,
    /// Unix seconds after which it opens nothing.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expires: Option<u64>,
    /// Requests a second it may make, sustained (none: no limit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rate: Option<f64>,
    /// Requests it may make at once above the rate (default: the rate, at least 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub burst: Option<f64>,
    /// It may also read `/metrics`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub admin: bool,
    /// A note for people (whose key, what for).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
}

impl KeyRecord {
    /// A record opening `archives` (names or globs) with no other rule; [`KeyFile::add`]
    /// gives it its id and hash.
    pub fn opening<S: Into<String>>(archives: impl IntoIterator<Item = S>) -> Self {
        Self {
            id: String::new(),
            hash: String::new(),
            archives: archives.into_iter().map(Into::into).collect(),
            origins: vec![],
            expires: None,
            rate: None,
            burst: None,
            admin: false,
            note: String::new(),
        }
    }
}

/// The keys file.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyFile {
    /// The keys.
    #[serde(default, rename = "key")]
    pub keys: Vec<KeyRecord>,
}

/// Why a keys file cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum KeysError {
    /// Reading or writing it failed.
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// What failed.
        error: std::io::Error,
    },
    /// Its content is not a keys file.
    #[error("{path}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the line or key.
        reason: String,
    },
    /// The system's random source failed.
    #[error("the system's random source failed")]
    Random,
}

impl KeyFile {
    /// Reads a keys file; a file that does not exist holds no key.
    ///
    /// # Errors
    /// [`KeysError`] naming the file, and the key at fault.
    pub fn read(path: &Path) -> Result<Self, KeysError> {
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Self::default()),
            Err(error) => return Err(KeysError::File { path: path.to_owned(), error }),
        };
        let invalid = |reason: String| KeysError::Invalid { path: path.to_owned(), reason };
        let file: Self = toml::from_str(&text).map_err(|e| invalid(e.to_string()))?;
        for k in &file.keys {
            if unhex::<4>(&k.id).is_none() || unhex::<32>(&k.hash).is_none() {
                return Err(invalid(format!("key {:?}: id is 8 hexadecimal digits, hash 64", k.id)));
            }
            if k.rate.is_some_and(|r| !(r > 0.0 && r.is_finite())) || k.burst.is_some_and(|b| b.is_nan() || b < 1.0) {
                return Err(invalid(format!("key {}: rate is above 0, burst at least 1", k.id)));
            }
        }
        Ok(file)
    }

    /// Writes the file (temporary name, then renamed; readable by its owner only).
    ///
    /// # Errors
    /// [`KeysError::File`] naming the file.
    pub fn write(&self, path: &Path) -> Result<(), KeysError> {
        let file = |error| KeysError::File { path: path.to_owned(), error };
        let text = toml::to_string_pretty(self).map_err(|e| file(std::io::Error::other(e)))?;
        let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let mut temp = tempfile::NamedTempFile::new_in(folder).map_err(file)?;
        std::io::Write::write_all(&mut temp, text.as_bytes()).map_err(file)?;
        temp.persist(path).map_err(|e| file(e.error))?;
        Ok(())
    }

    /// Makes a new key from `record`'s rules (its `id` and `hash` are filled in), adds it,
    /// and returns the key itself: the only time it is ever seen.
    ///
    /// # Errors
    /// [`KeysError::Random`].
    pub fn add(&mut self, mut record: KeyRecord) -> Result<String, KeysError> {
        let random = SystemRandom::new();
        let mut bytes = [0u8; 36];
        random.fill(&mut bytes).map_err(|_| KeysError::Random)?;
        let mut id = hex(&bytes[..4]);
        while self.keys.iter().any(|k| k.id == id) {
            random.fill(&mut bytes[..4]).map_err(|_| KeysError::Random)?;
            id = hex(&bytes[..4]);
        }
        let key = format!("tk_{id}_{}", hex(&bytes[4..]));
        record.id = id;
        record.hash = hex(digest::digest(&digest::SHA256, key.as_bytes()).as_ref());
        self.keys.push(record);
        Ok(key)
    }
}

/// The keys, ready to check a presented key.
#[derive(Debug, Default)]
pub struct KeyStore {
    keys: Vec<Stored>,
    /// Each key's index, by id.
    by_id: HashMap<String, usize, BuildHasherDefault<IdHasher>>,
}

/// FNV-1a: ids are a few hex digits the operator's file gives, looked up on every request
/// (SipHash's resistance to chosen collisions is not needed for a map the server builds
/// from its own file, and cost a tenth of a decision).
#[derive(Default)]
struct IdHasher(u64);

impl std::hash::Hasher for IdHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        let mut h = if self.0 == 0 { 0xcbf2_9ce4_8422_2325 } else { self.0 };
        for &b in bytes {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
        self.0 = h;
    }
}

#[derive(Debug)]
struct Stored {
    record: Arc<KeyRecord>,
    hash: [u8; 32],
    /// The key itself, once presented and found by its hash: later requests compare with
    /// it (constant time) instead of hashing (a SHA-256 is a fifth of a tile answer's CPU).
    verified: OnceLock<String>,
}

/// A hash no key has: what an unknown key is compared against, so that it costs the time
/// a known one does.
const NO_HASH: [u8; 32] = [0; 32];

impl KeyStore {
    /// The keys of a file.
    pub fn new(file: KeyFile) -> Self {
        let keys: Vec<Stored> = file
            .keys
            .into_iter()
            .filter_map(|k| {
                Some(Stored { hash: unhex::<32>(&k.hash)?, record: Arc::new(k), verified: OnceLock::new() })
            })
            .collect();
        let by_id = keys.iter().enumerate().map(|(i, k)| (k.record.id.clone(), i)).collect();
        Self { keys, by_id }
    }

    /// A copy that shares nothing with this one (its records are new allocations): each
    /// serving thread decides with its own, so taking a record counts references on
    /// memory no other core writes.
    pub fn private_copy(&self) -> Self {
        let keys = self
            .keys
            .iter()
            .map(|k| Stored {
                record: Arc::new(KeyRecord::clone(&k.record)),
                hash: k.hash,
                verified: k.verified.get().map(|v| OnceLock::from(v.clone())).unwrap_or_default(),
            })
            .collect();
        Self { keys, by_id: self.by_id.clone() }
    }

    /// How many keys there are.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// The record of `key`, if it is one of these (compared in constant time: with the key
    /// once verified, else by its hash).
    pub fn find(&self, key: &str) -> Option<Arc<KeyRecord>> {
        let id = key.strip_prefix("tk_").and_then(|rest| rest.split_once('_')).map(|(id, _)| id);
        let found = id.and_then(|id| self.by_id.get(id)).map(|&i| &self.keys[i]);
        if let Some(known) = found.and_then(|k| k.verified.get()) {
            let same = constant_time_eq(known.as_bytes(), key.as_bytes());
            return found.filter(|_| same).map(|k| Arc::clone(&k.record));
        }
        let hash = digest::digest(&digest::SHA256, key.as_bytes());
        let expected = found.map_or(&NO_HASH, |k| &k.hash);
        let same = constant_time_eq(hash.as_ref(), expected);
        let found = found.filter(|_| same)?;
        let _ = found.verified.set(key.to_owned());
        Some(Arc::clone(&found.record))
    }
}

/// Whether two byte strings are equal, in a time that depends on their length only (every
/// byte is compared; no early exit the optimizer could bring back).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    // Eight bytes at a time, then the rest.
    let word = |c: &[u8]| c.iter().fold(0u64, |w, &b| (w << 8) | u64::from(b));
    let (wa, wb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail = wa.remainder().iter().zip(wb.remainder()).fold(0u64, |d, (x, y)| d | u64::from(x ^ y));
    let diff = wa.zip(wb).fold(tail, |d, (x, y)| d | (word(x) ^ word(y)));
    std::hint::black_box(diff) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(archives: &[&str]) -> KeyRecord {
        KeyRecord::opening(archives.iter().copied())
    }

    #[test]
    fn a_key_is_stored_as_its_hash_and_found_only_whole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys.toml");
        let mut file = KeyFile::read(&path).unwrap();
        let key = file.add(record(&["valley"])).unwrap();
        let other = file.add(record(&["survey-*"])).unwrap();
        file.write(&path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(!text.contains(&key[12..]) && !text.contains(&other[12..]), "no key in plain text: {text}");
        let store = KeyStore::new(KeyFile::read(&path).unwrap());
        assert_eq!(store.find(&key).map(|k| k.archives.clone()), Some(vec!["valley".to_owned()]));
        assert_eq!(store.find(&other).map(|k| k.archives.clone()), Some(vec!["survey-*".to_owned()]));
        let mut wrong = key.clone();
        wrong.pop();
        wrong.push(if key.ends_with('0') { '1' } else { '0' });
        for bad in [wrong.as_str(), &key[..key.len() - 1], "tk_", "", "tk_00000000_00", &key.replace("tk_", "tx_")] {
            assert!(store.find(bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn a_bad_keys_file_names_itself_and_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys.toml");
        std::fs::write(&path, "[[key]]\nid = \"zz\"\nhash = \"00\"\narchives = []\n").unwrap();
        let e = KeyFile::read(&path).unwrap_err().to_string();
        assert!(e.contains("keys.toml") && e.contains("\"zz\""), "{e}");
        std::fs::write(&path, "[[key]]\nidd = 1\n").unwrap();
        assert!(KeyFile::read(&path).unwrap_err().to_string().contains("idd"));
    }
}
