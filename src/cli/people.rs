//! Numbers, names and places as people read them: sensible precision, units, absent
//! values left out (`--json` keeps every digit).

/// `v` with about `digits` significant digits, no trailing zeros, no exponent:
/// 921.4499999999999 -> `921.4`, 30.0 -> `30`.
pub fn significant(v: f64, digits: i32) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    #[expect(clippy::cast_possible_truncation, reason = "a decimal exponent of a finite f64")]
    let magnitude = v.abs().log10().floor() as i32;
    let decimals = usize::try_from((digits - 1 - magnitude).max(0)).unwrap_or(0);
    trim(format!("{v:.decimals$}"))
}

/// `v` with at most `decimals` decimals, trailing zeros dropped.
pub fn fixed(v: f64, decimals: usize) -> String {
    trim(format!("{v:.decimals$}"))
}

fn trim(text: String) -> String {
    if !text.contains('.') {
        return text;
    }
    let t = text.trim_end_matches('0').trim_end_matches('.');
    if t == "-0" { "0".to_owned() } else { t.to_owned() }
}

/// A length in metres: `921.4 m`, `235.9 km` (kilometres from 10 km).
pub fn length(metres: f64) -> String {
    if metres.abs() >= 10_000.0 {
        format!("{} km", significant(metres / 1000.0, 4))
    } else {
        format!("{} m", significant(metres, 4))
    }
}

/// A height in metres, to the decimetre: `-12.5 m`, `2345 m`.
pub fn height(metres: f64) -> String {
    format!("{} m", fixed(metres, 1))
}

/// A byte count: `512 B`, `1.5 KiB`, `12.3 MiB`.
pub fn bytes(bytes: u64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB"];
    #[expect(clippy::cast_precision_loss, reason = "a size shown to one decimal")]
    let mut v = bytes as f64;
    let mut unit = 0;
    while v >= 1024.0 && unit + 1 < units.len() {
        v /= 1024.0;
        unit += 1;
    }
    if unit == 0 { format!("{bytes} B") } else { format!("{v:.1} {}", units[unit]) }
}

/// A serde enum's own name (`raw_u16`, `elevation`): what the metadata and the flags say.
pub fn name<T: serde::Serialize>(value: &T) -> String {
    match serde_json::to_value(value) {
        Ok(serde_json::Value::String(s)) => s,
        _ => "?".to_owned(),
    }
}

/// A CRS as the metadata names it (`EPSG:32610`, a PROJ definition), for people: what it
/// is and its code; the text itself when it names no CRS this build knows.
pub fn crs(text: &str) -> String {
    terrastream_crs::Crs::parse(text).map_or_else(|_| text.to_owned(), |c| c.label())
}

/// West, south, east, north in degrees: `122.64181°W to 122.45819°W, 37.81237°N to
/// 37.96681°N` (five decimals: about a metre).
pub fn lon_lat_box([w, s, e, n]: [f64; 4]) -> String {
    let lon = |v: f64| format!("{}°{}", fixed(v.abs(), 5), if v < 0.0 { 'W' } else { 'E' });
    let lat = |v: f64| format!("{}°{}", fixed(v.abs(), 5), if v < 0.0 { 'S' } else { 'N' });
    format!("{} to {}, {} to {}", lon(w), lon(e), lat(s), lat(n))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_read_as_people_write_them() {
        assert_eq!(significant(921.449_999_999_999_9, 4), "921.4");
        assert_eq!(significant(30.0, 4), "30");
        assert_eq!(significant(0.000_123_45, 3), "0.000123");
        assert_eq!(length(235_891.199_999_999_98), "235.9 km");
        assert_eq!(length(9_999.0), "9999 m");
        assert_eq!(height(-0.04), "0 m");
        assert_eq!(height(784.125), "784.1 m");
        assert_eq!(bytes(1536), "1.5 KiB");
        assert_eq!(name(&terrastream_format::TileFormat::RawU16), "raw_u16");
        assert_eq!(crs("EPSG:4326"), "longitude/latitude, WGS 84 (EPSG:4326)");
        assert_eq!(crs("not a crs"), "not a crs");
        assert_eq!(
            lon_lat_box([-122.641_805_555_555_55, 37.8, -122.5, 37.966_805_555_555_55]),
            "122.64181°W to 122.5°W, 37.8°N to 37.96681°N"
        );
    }
}
