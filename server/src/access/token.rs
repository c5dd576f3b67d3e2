//! Signed tokens: an expiring grant for one archive or one path prefix, made from a shared
//! secret (HMAC-SHA-256), so that a link can be handed out without a key and a CDN can
//! cache by URL.
//!
//! A token reads `ts1~{expires}~{scope}~{signature}`: `expires` in Unix seconds, `scope` an
//! archive's name (`valley`: every route of that archive, and no other) or a path prefix
//! ending in `/` (`/valley/xyz/`: only the paths under it), `signature` the HMAC of
//! `ts1~{expires}~{scope}` as 64 hexadecimal digits. Every character is URL-safe, so a
//! token goes in a query parameter as it is.

use ring::hmac;

/// The tokens' version tag.
const VERSION: &str = "ts1";

/// Longest token accepted (a scope is a path prefix, short in practice).
pub const MAX_TOKEN_LEN: usize = 512;

/// What a signed token grants.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Scope {
    /// Every route of one archive (or manifest), by its exact name.
    Archive(String),
    /// Every path under this prefix (which ends in `/`).
    Prefix(String),
}

impl Scope {
    /// The scope a text names: a prefix when it starts with `/` (and then must end with
    /// one), else an archive's name.
    ///
    /// # Errors
    /// Why the text names no scope.
    pub fn parse(text: &str) -> Result<Self, String> {
        let safe = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-' | '/');
        if text.is_empty() || !text.chars().all(safe) {
            return Err(format!("{text:?}: a scope is an archive's name or a path prefix (letters, digits, . _ - /)"));
        }
        if text.starts_with('/') {
            if !text.ends_with('/') || text.contains("//") || text.split('/').any(|s| s == "." || s == "..") {
                return Err(format!("{text:?}: a path prefix ends with '/' and has no empty, '.' or '..' segment"));
            }
            Ok(Self::Prefix(text.to_owned()))
        } else if text.contains('/') {
            Err(format!("{text:?}: an archive's name has no '/' (a path prefix starts with one)"))
        } else {
            Ok(Self::Archive(text.to_owned()))
        }
    }

    fn text(&self) -> &str {
        match self {
            Self::Archive(s) | Self::Prefix(s) => s,
        }
    }
}

/// A token's parts, read but not yet checked.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Signed {
    /// Unix seconds after which it no longer opens anything.
    pub expires: u64,
    /// What it opens.
    pub scope: Scope,
    signature: [u8; 32],
}

/// Why a token was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refused {
    /// Not a token of this form.
    Malformed,
    /// Its signature is not this secret's.
    BadSignature,
    /// Past its expiry (beyond the allowed clock skew).
    Expired,
}

/// Makes the token granting `scope` until `expires` (Unix seconds).
pub fn sign(secret: &[u8], scope: &Scope, expires: u64) -> String {
    let body = format!("{VERSION}~{expires}~{}", scope.text());
    let tag = hmac::sign(&hmac::Key::new(hmac::HMAC_SHA256, secret), body.as_bytes());
    format!("{body}~{}", hex(tag.as_ref()))
}

/// Reads a token's parts (nothing checked but its form).
///
/// # Errors
/// [`Refused::Malformed`] for anything not of the token's form.
pub fn parse(token: &str) -> Result<Signed, Refused> {
    if token.len() > MAX_TOKEN_LEN {
        return Err(Refused::Malformed);
    }
    let mut parts = token.split('~');
    let (Some(VERSION), Some(expires), Some(scope), Some(signature), None) =
        (parts.next(), parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(Refused::Malformed);
    };
    if expires.is_empty() || expires.len() > 20 || !expires.bytes().all(|b| b.is_ascii_digit()) {
        return Err(Refused::Malformed);
    }
    let expires = expires.parse().map_err(|_| Refused::Malformed)?;
    let scope = Scope::parse(scope).map_err(|_| Refused::Malformed)?;
    let signature = unhex::<32>(signature).ok_or(Refused::Malformed)?;
    Ok(Signed { expires, scope, signature })
}

/// Checks a token against `secret` at `now` (Unix seconds), allowing `skew` seconds of
/// clock difference past its expiry; the scope it grants.
///
/// # Errors
/// Why it opens nothing.
pub fn verify(secret: &[u8], token: &str, now: u64, skew: u64) -> Result<Scope, Refused> {
    let signed = parse(token)?;
    let body = format!("{VERSION}~{}~{}", signed.expires, signed.scope.text());
    // Constant time: ring compares the tags without an early exit.
    hmac::verify(&hmac::Key::new(hmac::HMAC_SHA256, secret), body.as_bytes(), &signed.signature)
        .map_err(|_| Refused::BadSignature)?;
    if now > signed.expires.saturating_add(skew) {
        return Err(Refused::Expired);
    }
    Ok(signed.scope)
}

/// Lower-case hexadecimal.
pub(crate) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// `N` bytes from exactly `2N` hexadecimal digits.
pub(crate) fn unhex<const N: usize>(text: &str) -> Option<[u8; N]> {
    let digits = text.as_bytes();
    if digits.len() != 2 * N {
        return None;
    }
    let value = |d: u8| char::from(d).to_digit(16).and_then(|v| u8::try_from(v).ok());
    let mut out = [0u8; N];
    for (o, pair) in out.iter_mut().zip(digits.chunks_exact(2)) {
        *o = value(pair[0])? << 4 | value(pair[1])?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SECRET: &[u8] = b"a shared secret of the operator";

    #[test]
    fn a_token_opens_its_scope_until_it_expires() {
        let scope = Scope::parse("valley").unwrap();
        let token = sign(SECRET, &scope, 1_000);
        assert!(token.starts_with("ts1~1000~valley~") && token.len() == 16 + 64, "{token}");
        assert_eq!(verify(SECRET, &token, 999, 0), Ok(scope.clone()));
        assert_eq!(verify(SECRET, &token, 1_000, 0), Ok(scope.clone()));
        assert_eq!(verify(SECRET, &token, 1_001, 0), Err(Refused::Expired));
        assert_eq!(verify(SECRET, &token, 1_030, 60), Ok(scope), "within the clock skew");
        assert_eq!(verify(b"another secret", &token, 0, 0), Err(Refused::BadSignature));
    }

    #[test]
    fn a_changed_token_opens_nothing() {
        let token = sign(SECRET, &Scope::parse("valley").unwrap(), 1_000);
        for forged in [
            token.replace("valley", "other1"),
            token.replace("~1000~", "~9000~"),
            token.replace("ts1~", "ts2~"),
            format!("{token}0"),
            token[..token.len() - 1].to_owned(),
            format!("{token}~x"),
            token.to_uppercase(),
            String::new(),
            "ts1~~valley~".to_owned(),
            format!("ts1~{}~valley~{}", "9".repeat(30), "0".repeat(64)),
        ] {
            assert!(verify(SECRET, &forged, 0, 0).is_err(), "{forged}");
        }
    }

    #[test]
    fn scopes_are_names_or_prefixes_ending_in_a_slash() {
        assert_eq!(Scope::parse("/valley/xyz/"), Ok(Scope::Prefix("/valley/xyz/".into())));
        for bad in ["", "/valley", "a/b", "/a/../b/", "//", "val ley", "va~l", "/a//b/", "/./"] {
            assert!(Scope::parse(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn hex_round_trips() {
        assert_eq!(unhex::<2>(&hex(&[0xab, 0x01])), Some([0xab, 0x01]));
        assert_eq!(unhex::<2>("ab0"), None);
        assert_eq!(unhex::<1>("zz"), None);
    }
}
