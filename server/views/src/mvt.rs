//! Mapbox Vector Tile 2.1 encoding (protobuf, written by hand): one layer of line
//! features with integer and boolean properties, what contour tiles need.

/// One line feature: its vertices (tile units) and its properties.
#[derive(Clone, Debug, PartialEq)]
pub struct Line {
    /// Vertices in tile units (0..extent across the tile; beyond it in the buffer).
    pub points: Vec<(i32, i32)>,
    /// Properties: name and value.
    pub properties: Vec<(&'static str, Value)>,
}

/// A property's value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Value {
    /// A number (written as `double` unless whole, then `sint`).
    Number(f64),
    /// A flag.
    Bool(bool),
}

impl Value {
    /// The number, if it is one.
    #[must_use]
    pub fn number(self) -> Option<f64> {
        match self {
            Value::Number(n) => Some(n),
            Value::Bool(_) => None,
        }
    }
}

/// The tile: one layer `name` of `lines`, `extent` units a side.
pub fn encode(name: &str, extent: u32, lines: &[Line]) -> Vec<u8> {
    let mut keys: Vec<&str> = vec![];
    let mut values: Vec<Value> = vec![];
    let mut layer = Vec::with_capacity(64 + lines.iter().map(|l| 16 + 4 * l.points.len()).sum::<usize>());
    varint_field(&mut layer, 15, 2);
    bytes_field(&mut layer, 1, name.as_bytes());
    // Each feature written in place: its tags and geometry first into buffers kept from
    // feature to feature, then the feature's length, then them.
    let (mut tags, mut geometry) = (Vec::new(), Vec::new());
    for (id, line) in lines.iter().enumerate().filter(|(_, l)| l.points.len() >= 2) {
        tags.clear();
        for (key, value) in &line.properties {
            let k = keys.iter().position(|k| k == key).unwrap_or_else(|| {
                keys.push(key);
                keys.len() - 1
            });
            let v = values.iter().position(|v| v == value).unwrap_or_else(|| {
                values.push(*value);
                values.len() - 1
            });
            varint(&mut tags, k as u64);
            varint(&mut tags, v as u64);
        }
        geometry.clear();
        line_geometry(&mut geometry, &line.points);
        let id = id as u64 + 1;
        let length = 1 + varint_len(id) + field_len(&tags) + 2 + field_len(&geometry);
        varint(&mut layer, 2 << 3 | 2);
        varint(&mut layer, length as u64);
        varint_field(&mut layer, 1, id);
        bytes_field(&mut layer, 2, &tags);
        varint_field(&mut layer, 3, 2); // LINESTRING
        bytes_field(&mut layer, 4, &geometry);
    }
    for k in &keys {
        bytes_field(&mut layer, 3, k.as_bytes());
    }
    for v in &values {
        let mut value = Vec::new();
        match *v {
            #[expect(clippy::cast_possible_truncation, reason = "whole numbers within i64")]
            Value::Number(n) if n.fract() == 0.0 && n.abs() < 9e15 => varint_field(&mut value, 6, zigzag(n as i64)),
            Value::Number(n) => {
                value.push(3 << 3 | 1);
                value.extend_from_slice(&n.to_le_bytes());
            }
            Value::Bool(b) => varint_field(&mut value, 7, u64::from(b)),
        }
        bytes_field(&mut layer, 4, &value);
    }
    varint_field(&mut layer, 5, u64::from(extent));
    let mut tile = Vec::with_capacity(layer.len() + 8);
    bytes_field(&mut tile, 3, &layer);
    tile
}

/// Bytes of `v` as a varint.
fn varint_len(v: u64) -> usize {
    (64 - (v | 1).leading_zeros() as usize).div_ceil(7)
}

/// Bytes of a length-delimited field (of a number below 16) holding `bytes`.
fn field_len(bytes: &[u8]) -> usize {
    1 + varint_len(bytes.len() as u64) + bytes.len()
}

/// A line's commands: MoveTo the first vertex, LineTo the others (deltas, zig-zag).
fn line_geometry(out: &mut Vec<u8>, points: &[(i32, i32)]) {
    let mut cursor = (0i64, 0i64);
    let mut put = |out: &mut Vec<u8>, &(x, y): &(i32, i32)| {
        let (x, y) = (i64::from(x), i64::from(y));
        varint(out, zigzag(x - cursor.0));
        varint(out, zigzag(y - cursor.1));
        cursor = (x, y);
    };
    varint(out, 1 | 1 << 3);
    put(out, &points[0]);
    varint(out, 2 | ((points.len() as u64 - 1) << 3));
    for p in &points[1..] {
        put(out, p);
    }
}

#[expect(clippy::cast_sign_loss, reason = "zig-zag: the sign moves to the lowest bit")]
pub(crate) fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

#[expect(clippy::cast_possible_truncation, reason = "seven bits at a time")]
pub(crate) fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

pub(crate) fn varint_field(out: &mut Vec<u8>, field: u64, v: u64) {
    varint(out, field << 3);
    varint(out, v);
}

pub(crate) fn bytes_field(out: &mut Vec<u8>, field: u64, bytes: &[u8]) {
    varint(out, field << 3 | 2);
    varint(out, bytes.len() as u64);
    out.extend_from_slice(bytes);
}

/// A tile read back: each feature's properties and vertices (for tests and for checking
/// what was written; an independent reader is the clients').
///
/// # Errors
/// Where the bytes are not such a tile.
pub fn decode(bytes: &[u8]) -> Result<Vec<Line>, String> {
    let mut lines = Vec::new();
    let mut r = Reader(bytes);
    while let Some((field, data)) = r.field()? {
        if field != 3 {
            continue;
        }
        let Data::Bytes(layer) = data else { return Err("a layer that is not a message".into()) };
        let (mut keys, mut values, mut features) = (vec![], vec![], vec![]);
        let mut l = Reader(layer);
        while let Some((field, data)) = l.field()? {
            match (field, data) {
                (2, Data::Bytes(f)) => features.push(f),
                (3, Data::Bytes(k)) => keys.push(std::str::from_utf8(k).map_err(|e| e.to_string())?.to_owned()),
                (4, Data::Bytes(v)) => values.push(value_of(v)?),
                _ => {}
            }
        }
        for f in features {
            lines.push(feature_of(f, &keys, &values)?);
        }
    }
    Ok(lines)
}

fn value_of(bytes: &[u8]) -> Result<Value, String> {
    let mut r = Reader(bytes);
    match r.field()? {
        Some((3, Data::Fixed64(b))) => Ok(Value::Number(f64::from_le_bytes(b))),
        #[expect(clippy::cast_precision_loss, clippy::cast_possible_wrap, reason = "test-sized values")]
        Some((6, Data::Varint(v))) => Ok(Value::Number(((v >> 1) as i64 ^ -((v & 1) as i64)) as f64)),
        Some((7, Data::Varint(v))) => Ok(Value::Bool(v != 0)),
        other => Err(format!("an unexpected value {other:?}")),
    }
}

fn feature_of(bytes: &[u8], keys: &[String], values: &[Value]) -> Result<Line, String> {
    let (mut tags, mut geometry) = (vec![], vec![]);
    let mut r = Reader(bytes);
    while let Some((field, data)) = r.field()? {
        match (field, data) {
            (2, Data::Bytes(t)) => tags = Reader(t).varints()?,
            (4, Data::Bytes(g)) => geometry = Reader(g).varints()?,
            _ => {}
        }
    }
    let mut properties = vec![];
    for pair in tags.chunks_exact(2) {
        let index = |v: u64| usize::try_from(v).unwrap_or(usize::MAX);
        let key = keys.get(index(pair[0])).ok_or("a tag's key out of range")?;
        let value = *values.get(index(pair[1])).ok_or("a tag's value out of range")?;
        let key: &'static str = match key.as_str() {
            "ele" => "ele",
            "major" => "major",
            _ => "other",
        };
        properties.push((key, value));
    }
    let mut points = vec![];
    let (mut x, mut y, mut i) = (0i64, 0i64, 0);
    #[expect(clippy::cast_possible_wrap, reason = "zig-zag deltas of i32 vertices")]
    let unzig = |v: u64| (v >> 1) as i64 ^ -((v & 1) as i64);
    while i < geometry.len() {
        let (command, count) = (geometry[i] & 7, geometry[i] >> 3);
        i += 1;
        if command == 7 {
            continue;
        }
        for _ in 0..count {
            let (dx, dy) = (*geometry.get(i).ok_or("cut geometry")?, *geometry.get(i + 1).ok_or("cut geometry")?);
            (x, y) = (x + unzig(dx), y + unzig(dy));
            points.push((i32::try_from(x).map_err(|e| e.to_string())?, i32::try_from(y).map_err(|e| e.to_string())?));
            i += 2;
        }
    }
    Ok(Line { points, properties })
}

#[derive(Debug)]
enum Data<'a> {
    Varint(u64),
    Fixed64([u8; 8]),
    Bytes(&'a [u8]),
}

struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn varint(&mut self) -> Result<u64, String> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let (&b, rest) = self.0.split_first().ok_or("a cut varint")?;
            self.0 = rest;
            v |= u64::from(b & 0x7f) << shift;
            if b < 0x80 {
                return Ok(v);
            }
        }
        Err("a varint over 64 bits".into())
    }

    fn varints(&mut self) -> Result<Vec<u64>, String> {
        let mut out = vec![];
        while !self.0.is_empty() {
            out.push(self.varint()?);
        }
        Ok(out)
    }

    fn field(&mut self) -> Result<Option<(u64, Data<'a>)>, String> {
        if self.0.is_empty() {
            return Ok(None);
        }
        let key = self.varint()?;
        let data = match key & 7 {
            0 => Data::Varint(self.varint()?),
            1 => {
                let (b, rest) = self.0.split_at_checked(8).ok_or("a cut fixed64")?;
                self.0 = rest;
                Data::Fixed64(b.try_into().map_err(|_| "fixed64")?)
            }
            2 => {
                let len = usize::try_from(self.varint()?).map_err(|e| e.to_string())?;
                let (b, rest) = self.0.split_at_checked(len).ok_or("a cut field")?;
                self.0 = rest;
                Data::Bytes(b)
            }
            other => return Err(format!("wire type {other}")),
        };
        Ok(Some((key >> 3, data)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_round_trip() {
        let lines = vec![
            Line {
                points: vec![(0, 0), (10, -5), (4096, 300)],
                properties: vec![("ele", Value::Number(100.0)), ("major", Value::Bool(true))],
            },
            Line {
                points: vec![(-64, 7), (3, 3)],
                properties: vec![("ele", Value::Number(12.5)), ("major", Value::Bool(false))],
            },
        ];
        let bytes = encode("contours", 4096, &lines);
        assert_eq!(decode(&bytes).unwrap(), lines);
        assert!(decode(&bytes[..bytes.len() - 1]).is_err());
    }
}
