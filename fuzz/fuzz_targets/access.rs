//! Any bytes as a request's credentials and target: the signed-token parser, and the access
//! rules' one decision on a path, query, `Authorization`, `Origin` and `Referer` (split at
//! NUL bytes) with every archive private. Must never panic; without a valid credential it
//! must never allow a private archive; a token that parses must print back to itself.
#![no_main]

use std::sync::OnceLock;
use std::time::SystemTime;

use libfuzzer_sys::fuzz_target;
use terrastream_server::access::token::{self, Scope};
use terrastream_server::access::{Access, Presented, Rules};

const SECRET: &[u8] = b"the fuzzer's signing secret, 32 b";

fn access() -> &'static Access {
    static ACCESS: OnceLock<Access> = OnceLock::new();
    ACCESS.get_or_init(|| {
        let secret = std::env::temp_dir().join(format!("terrastream-fuzz-secret-{}", std::process::id()));
        std::fs::write(&secret, SECRET).expect("a temporary file");
        let rules = Rules { private_all: true, secret: Some(secret), ..Rules::default() };
        Access::new(rules).expect("the rules")
    })
}

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(signed) = token::parse(text) {
            let scope = Scope::parse(match &signed.scope {
                Scope::Archive(s) | Scope::Prefix(s) => s,
            });
            assert_eq!(scope.as_ref(), Ok(&signed.scope));
        }
        let _ = token::verify(SECRET, text, 0, 60);
    }
    let mut parts = data.split(|&b| b == 0);
    let (Some(path), query, authorization, origin, referer) =
        (parts.next().and_then(|p| std::str::from_utf8(p).ok()), parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return;
    };
    let query = query.and_then(|q| std::str::from_utf8(q).ok());
    let req = Presented { path, query, authorization, origin, referer };
    if let Ok(grant) = access().decide(&req, SystemTime::now()) {
        // Without a key file, only a token signed with the secret opens a private archive;
        // the fuzzer cannot forge one, so an allowed request names no archive at all.
        assert!(!grant.private, "{req:?} allowed into a private archive");
    }
});
