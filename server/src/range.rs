//! RFC 9110 `Range` and conditional requests, with nginx's choices where the RFC leaves
//! room (nginx is the reference behaviour our tests compare against):
//! a malformed `Range` is 416; more ranges than `max_ranges`, ranges adding up to more
//! than the file, or a `Range` that is not `bytes=` are answered with the whole file.

use std::ops::Range;
use std::time::SystemTime;

use axum::http::HeaderMap;
use axum::http::header::{IF_MATCH, IF_MODIFIED_SINCE, IF_NONE_MATCH, IF_RANGE, IF_UNMODIFIED_SINCE};

/// How to answer a `Range` header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RangeOutcome {
    /// 200 with the whole file.
    Full,
    /// 206 with these ranges (one: `Content-Range`; several: multipart/byteranges).
    Partial(Vec<Range<u64>>),
    /// 416 with `Content-Range: bytes */len`.
    Unsatisfiable,
}

fn digits(p: &[u8], i: &mut usize, value: &mut u64) -> bool {
    let start = *i;
    while let Some(d) = p.get(*i).filter(|c| c.is_ascii_digit()) {
        match value.checked_mul(10).and_then(|v| v.checked_add(u64::from(d - b'0'))) {
            Some(v) => *value = v,
            None => return false,
        }
        *i += 1;
    }
    *i > start
}

fn spaces(p: &[u8], i: &mut usize) {
    while p.get(*i) == Some(&b' ') {
        *i += 1;
    }
}

/// Parses a `Range` header value for a representation of `len` bytes.
pub fn parse_range(value: &[u8], len: u64, max_ranges: usize) -> RangeOutcome {
    // As nginx: a bare "bytes=" is ignored, not malformed.
    if value.len() < 7 || !value[..6].eq_ignore_ascii_case(b"bytes=") {
        return RangeOutcome::Full;
    }
    let p = &value[6..];
    let mut i = 0;
    let mut ranges = Vec::new();
    let mut total = 0u64;
    loop {
        let (mut start, mut end) = (0u64, 0u64);
        spaces(p, &mut i);
        let suffix = p.get(i) == Some(&b'-');
        let mut open = false;
        if suffix {
            i += 1;
        } else {
            if !digits(p, &mut i, &mut start) {
                return RangeOutcome::Unsatisfiable;
            }
            spaces(p, &mut i);
            if p.get(i) != Some(&b'-') {
                return RangeOutcome::Unsatisfiable;
            }
            i += 1;
            spaces(p, &mut i);
            if matches!(p.get(i), None | Some(b',')) {
                end = len;
                open = true;
            }
        }
        if !open {
            if !digits(p, &mut i, &mut end) {
                return RangeOutcome::Unsatisfiable;
            }
            spaces(p, &mut i);
            if !matches!(p.get(i), None | Some(b',')) {
                return RangeOutcome::Unsatisfiable;
            }
            if suffix {
                start = len.saturating_sub(end);
                end = len.saturating_sub(1);
            }
            end = if end >= len { len } else { end + 1 };
        }
        if start < end {
            total = total.saturating_add(end - start);
            ranges.push(start..end);
            if ranges.len() > max_ranges {
                return RangeOutcome::Full;
            }
        } else if start == 0 {
            return RangeOutcome::Full;
        }
        if p.get(i) != Some(&b',') {
            break;
        }
        i += 1;
    }
    if ranges.is_empty() {
        return RangeOutcome::Unsatisfiable;
    }
    if total > len {
        return RangeOutcome::Full;
    }
    RangeOutcome::Partial(ranges)
}

/// The answer to a request's preconditions (RFC 9110 §13.2.2 order).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Precondition {
    /// Go on.
    Proceed,
    /// 304 Not Modified.
    NotModified,
    /// 412 Precondition Failed.
    Failed,
}

fn etag_list_matches(list: &str, etag: &str, weak: bool) -> bool {
    list.split(',').map(str::trim).any(|candidate| {
        if candidate == "*" {
            return true;
        }
        match candidate.strip_prefix("W/") {
            Some(c) => weak && strip_weak(etag) == c,
            None => strip_weak(etag) == candidate && (weak || !etag.starts_with("W/")),
        }
    })
}

fn strip_weak(etag: &str) -> &str {
    etag.strip_prefix("W/").unwrap_or(etag)
}

fn date(headers: &HeaderMap, name: axum::http::HeaderName) -> Option<SystemTime> {
    httpdate::parse_http_date(headers.get(name)?.to_str().ok()?).ok()
}

fn seconds(t: SystemTime) -> u64 {
    t.duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

/// Does `If-None-Match` list `etag` (weak comparison, `*` included)? False without one.
pub fn if_none_match(headers: &HeaderMap, etag: &str) -> bool {
    headers.get(IF_NONE_MATCH).and_then(|v| v.to_str().ok()).is_some_and(|l| etag_list_matches(l, etag, true))
}

/// Evaluates If-Match, If-Unmodified-Since, If-None-Match and If-Modified-Since.
pub fn preconditions(headers: &HeaderMap, etag: &str, modified: SystemTime, safe_method: bool) -> Precondition {
    if let Some(v) = headers.get(IF_MATCH) {
        if !v.to_str().is_ok_and(|l| etag_list_matches(l, etag, false)) {
            return Precondition::Failed;
        }
    } else if let Some(since) = date(headers, IF_UNMODIFIED_SINCE)
        && seconds(modified) > seconds(since)
    {
        return Precondition::Failed;
    }
    if headers.contains_key(IF_NONE_MATCH) {
        if if_none_match(headers, etag) {
            return if safe_method { Precondition::NotModified } else { Precondition::Failed };
        }
    } else if let Some(since) = date(headers, IF_MODIFIED_SINCE)
        && safe_method
        && seconds(modified) <= seconds(since)
    {
        return Precondition::NotModified;
    }
    Precondition::Proceed
}

/// Does `If-Range` (if present) allow honouring `Range`? An entity tag must match
/// strongly, a date must equal `Last-Modified`.
pub fn if_range_allows(headers: &HeaderMap, etag: &str, modified: SystemTime) -> bool {
    let Some(v) = headers.get(IF_RANGE).and_then(|v| v.to_str().ok()) else { return true };
    let v = v.trim();
    if v.starts_with('"') || v.starts_with("W/") {
        return !v.starts_with("W/") && v == etag;
    }
    httpdate::parse_http_date(v).is_ok_and(|d| seconds(d) == seconds(modified))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r(v: &str) -> RangeOutcome {
        parse_range(v.as_bytes(), 1000, 4)
    }

    #[test]
    #[allow(clippy::single_range_in_vec_init)]
    fn ranges_follow_nginx() {
        use RangeOutcome::*;
        assert_eq!(r("bytes=0-99"), Partial(vec![0..100]));
        assert_eq!(r("bytes=900-"), Partial(vec![900..1000]));
        assert_eq!(r("bytes=-100"), Partial(vec![900..1000]));
        assert_eq!(r("bytes=-5000"), Partial(vec![0..1000]));
        assert_eq!(r("bytes=990-2000"), Partial(vec![990..1000]));
        assert_eq!(r("bytes=0-0,10-19"), Partial(vec![0..1, 10..20]));
        assert_eq!(r("BYTES= 1 - 2 , 5-6"), Partial(vec![1..3, 5..7]));
        assert_eq!(r("bytes=1000-"), Unsatisfiable);
        assert_eq!(r("bytes=1000-1001,2000-3000"), Unsatisfiable);
        assert_eq!(r("bytes=5-1,0-1"), Partial(vec![0..2]));
        assert_eq!(r("bytes=abc"), Unsatisfiable);
        assert_eq!(r("bytes=1-2;"), Unsatisfiable);
        assert_eq!(r("bytes=99999999999999999999999-"), Unsatisfiable);
        assert_eq!(r("items=0-1"), Full);
        assert_eq!(r("bytes="), Full);
        assert_eq!(r("bytes=0-1,2-3,4-5,6-7,8-9"), Full, "more than max_ranges");
        assert_eq!(r("bytes=0-999,0-999"), Full, "more bytes than the file");
        assert_eq!(parse_range(b"bytes=0-", 0, 4), Full);
        assert_eq!(r("bytes=-0"), Unsatisfiable);
    }

    #[test]
    fn preconditions_follow_rfc_9110() {
        let t = SystemTime::UNIX_EPOCH + std::time::Duration::from_secs(1_700_000_000);
        let h = |pairs: &[(&str, &str)]| {
            let mut m = HeaderMap::new();
            for (k, v) in pairs {
                m.insert(axum::http::HeaderName::from_bytes(k.as_bytes()).unwrap(), v.parse().unwrap());
            }
            m
        };
        let e = "\"abc\"";
        assert_eq!(preconditions(&h(&[("if-none-match", "\"abc\"")]), e, t, true), Precondition::NotModified);
        assert_eq!(preconditions(&h(&[("if-none-match", "W/\"abc\", \"x\"")]), e, t, true), Precondition::NotModified);
        assert_eq!(preconditions(&h(&[("if-none-match", "\"x\"")]), e, t, true), Precondition::Proceed);
        assert_eq!(preconditions(&h(&[("if-match", "\"x\"")]), e, t, true), Precondition::Failed);
        assert_eq!(preconditions(&h(&[("if-match", "W/\"abc\"")]), e, t, true), Precondition::Failed);
        assert_eq!(preconditions(&h(&[("if-match", "*")]), e, t, true), Precondition::Proceed);
        let later = httpdate::fmt_http_date(t + std::time::Duration::from_secs(5));
        let earlier = httpdate::fmt_http_date(t - std::time::Duration::from_secs(5));
        assert_eq!(preconditions(&h(&[("if-modified-since", &later)]), e, t, true), Precondition::NotModified);
        assert_eq!(preconditions(&h(&[("if-modified-since", &earlier)]), e, t, true), Precondition::Proceed);
        assert_eq!(preconditions(&h(&[("if-unmodified-since", &earlier)]), e, t, true), Precondition::Failed);
        assert!(if_range_allows(&h(&[("if-range", "\"abc\"")]), e, t));
        assert!(!if_range_allows(&h(&[("if-range", "\"old\"")]), e, t));
        assert!(if_range_allows(&h(&[("if-range", &httpdate::fmt_http_date(t))]), e, t));
        assert!(!if_range_allows(&h(&[("if-range", &later)]), e, t));
    }
}
