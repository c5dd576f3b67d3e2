//! `terrastream key` and `terrastream sign`: API keys in a keys file (hashes only), and
//! signed, expiring tokens from a shared secret.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use terrastream_server::access::keys::{KeyFile, KeyRecord};
use terrastream_server::access::token::{self, Scope};

#[derive(Debug, Subcommand)]
pub enum KeyCommand {
    /// Make a key and add it to the keys file; the key is printed once, never stored.
    New(NewKey),
    /// List the keys of a keys file (ids and rules; the keys themselves are not kept).
    List(KeysFile),
    /// Remove a key from the keys file (a server serving it drops it within a reload).
    Revoke(Revoke),
}

#[derive(Debug, Args)]
pub struct KeysFile {
    /// The keys file.
    #[arg(long, default_value = "keys.toml")]
    keys: PathBuf,
}

#[derive(Debug, Args)]
pub struct NewKey {
    /// Archive names or globs (`survey-*`) the key opens.
    #[arg(long, num_args = 1.., required = true)]
    archives: Vec<String>,
    /// HTTP origins it may be used from (`https://maps.example.com`); default: any.
    #[arg(long, num_args = 1..)]
    origins: Vec<String>,
    /// When it stops working: a duration from now (`30d`, `12h`, `90m`, `3600s`), a date
    /// (`2027-01-31`, UTC midnight) or Unix seconds.
    #[arg(long)]
    expires: Option<String>,
    /// Requests a second, sustained.
    #[arg(long)]
    rate: Option<f64>,
    /// Requests at once above the rate [default: the rate].
    #[arg(long, requires = "rate")]
    burst: Option<f64>,
    /// It may also read `/metrics`.
    #[arg(long)]
    admin: bool,
    /// A note for people: whose key, what for.
    #[arg(long, default_value = "")]
    note: String,
    #[command(flatten)]
    file: KeysFile,
}

#[derive(Debug, Args)]
pub struct Revoke {
    /// The key's id (`key list` shows them; the 8 digits after `tk_`).
    id: String,
    #[command(flatten)]
    file: KeysFile,
}

#[derive(Debug, Args)]
pub struct SignArgs {
    /// The file holding the shared secret (at least 16 bytes; the server's
    /// `--secret-file`).
    #[arg(long)]
    secret_file: PathBuf,
    /// The archive (or manifest) the token opens, by name.
    #[arg(long, conflicts_with = "prefix", required_unless_present = "prefix")]
    archive: Option<String>,
    /// The path prefix the token opens (`/valley/xyz/`; ends with `/`).
    #[arg(long)]
    prefix: Option<String>,
    /// How long it works: `30d`, `12h`, `90m`, `3600s`, a date or Unix seconds.
    #[arg(long, default_value = "1d")]
    expires: String,
    /// Print this URL with the token in its query instead of the token alone.
    #[arg(long)]
    url: Option<String>,
}

pub fn run(command: KeyCommand) -> Result<ExitCode> {
    match command {
        KeyCommand::New(args) => new_key(args),
        KeyCommand::List(args) => {
            let file = KeyFile::read(&args.keys)?;
            for k in &file.keys {
                let expires = k.expires.map_or_else(|| "never".to_owned(), |e| format!("at {e} (Unix seconds)"));
                let rate = k.rate.map_or_else(|| "no limit".to_owned(), |r| format!("{r}/s"));
                println!(
                    "tk_{}  archives {}  origins {}  expires {expires}  rate {rate}{}{}",
                    k.id,
                    k.archives.join(","),
                    if k.origins.is_empty() { "any".to_owned() } else { k.origins.join(",") },
                    if k.admin { "  admin" } else { "" },
                    if k.note.is_empty() { String::new() } else { format!("  ({})", k.note) }
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        KeyCommand::Revoke(args) => {
            let mut file = KeyFile::read(&args.file.keys)?;
            let id = args.id.trim_start_matches("tk_").split('_').next().unwrap_or("").to_owned();
            let before = file.keys.len();
            file.keys.retain(|k| k.id != id);
            if file.keys.len() == before {
                bail!("{}: no key {id:?}", args.file.keys.display());
            }
            file.write(&args.file.keys)?;
            println!("revoked tk_{id}");
            Ok(ExitCode::SUCCESS)
        }
    }
}

fn new_key(args: NewKey) -> Result<ExitCode> {
    if let Some(rate) = args.rate {
        anyhow::ensure!(rate > 0.0 && rate.is_finite(), "--rate {rate}: requests a second above 0");
    }
    if let Some(burst) = args.burst {
        anyhow::ensure!(burst >= 1.0, "--burst {burst}: at least 1");
    }
    for origin in &args.origins {
        anyhow::ensure!(
            origin.contains("://") && !origin.trim_end_matches('/').contains(['?', '#']),
            "--origins {origin:?}: an origin is scheme://host[:port]"
        );
    }
    let expires = args.expires.as_deref().map(|e| expiry(e, SystemTime::now())).transpose()?;
    let mut file = KeyFile::read(&args.file.keys)?;
    let key = file.add(KeyRecord {
        origins: args.origins.iter().map(|o| o.trim_end_matches('/').to_owned()).collect(),
        expires,
        rate: args.rate,
        burst: args.burst,
        admin: args.admin,
        note: args.note,
        ..KeyRecord::opening(args.archives)
    })?;
    file.write(&args.file.keys)?;
    eprintln!("{}: key added (shown once: keep it; the file holds its hash only)", args.file.keys.display());
    println!("{key}");
    Ok(ExitCode::SUCCESS)
}

pub fn sign(args: SignArgs) -> Result<ExitCode> {
    let secret = terrastream_server::access::read_secret(&args.secret_file)?;
    let scope = match (&args.archive, &args.prefix) {
        (Some(name), _) => Scope::parse(name),
        (None, Some(prefix)) => Scope::parse(prefix),
        (None, None) => bail!("--archive or --prefix"),
    }
    .map_err(anyhow::Error::msg)?;
    anyhow::ensure!(
        matches!((&scope, &args.archive), (Scope::Archive(_), Some(_)) | (Scope::Prefix(_), None)),
        "--archive names an archive (no '/'); --prefix is a path starting and ending with '/'"
    );
    let expires = expiry(&args.expires, SystemTime::now())?;
    let token = token::sign(&secret, &scope, expires);
    match args.url {
        Some(url) => println!("{url}{}access_token={token}", if url.contains('?') { '&' } else { '?' }),
        None => println!("{token}"),
    }
    Ok(ExitCode::SUCCESS)
}

/// Unix seconds of an expiry as people write it: a duration from `now` (`30d`, `12h`,
/// `90m`, `45s`), a date (`2027-01-31`: its start, UTC) or Unix seconds.
pub fn expiry(text: &str, now: SystemTime) -> Result<u64> {
    let text = text.trim();
    let now = now.duration_since(UNIX_EPOCH).context("the clock is before 1970")?.as_secs();
    let number = |digits: &str| digits.parse::<u64>().with_context(|| format!("{text:?}: not a number"));
    let unit = text.chars().last().filter(char::is_ascii_alphabetic);
    if let Some(unit) = unit {
        let seconds = match unit {
            'd' => 86_400,
            'h' => 3_600,
            'm' => 60,
            's' => 1,
            _ => bail!("{text:?}: a duration ends in d, h, m or s"),
        };
        let span = Duration::from_secs(number(&text[..text.len() - 1])?.saturating_mul(seconds));
        return Ok(now.saturating_add(span.as_secs()));
    }
    if let Some((y, rest)) = text.split_once('-') {
        let (m, d) = rest.split_once('-').with_context(|| format!("{text:?}: a date is YYYY-MM-DD"))?;
        let (y, m, d) = (number(y)?, number(m)?, number(d)?);
        anyhow::ensure!((1..=12).contains(&m) && (1..=31).contains(&d) && y >= 1970, "{text:?}: not a date");
        return Ok(days_from_civil(y, m, d) * 86_400);
    }
    number(text)
}

/// Days from 1970-01-01 to a date of the proleptic Gregorian calendar (Hinnant's
/// algorithm), for dates from 1970 on.
fn days_from_civil(y: u64, m: u64, d: u64) -> u64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y / 400;
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn expiries_read_as_people_write_them() {
        let now = UNIX_EPOCH + Duration::from_secs(1_000_000);
        assert_eq!(expiry("30d", now).unwrap(), 1_000_000 + 30 * 86_400);
        assert_eq!(expiry("12h", now).unwrap(), 1_000_000 + 12 * 3_600);
        assert_eq!(expiry("90m", now).unwrap(), 1_000_000 + 5_400);
        assert_eq!(expiry("1767225600", now).unwrap(), 1_767_225_600);
        assert_eq!(expiry("2026-01-01", now).unwrap(), 1_767_225_600);
        assert_eq!(expiry("2024-02-29", now).unwrap(), 1_709_164_800);
        for bad in ["", "d", "3w", "2026-13-01", "soon"] {
            assert!(expiry(bad, now).is_err(), "{bad}");
        }
    }
}
