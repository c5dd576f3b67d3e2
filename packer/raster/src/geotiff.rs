//! GeoTIFF tags: where a raster lies (model pixel scale, tiepoint, GeoKeys) and its GDAL
//! nodata value.

use std::path::Path;

use terrastream_format::Georeference;

use crate::error::{Error, Result};

const MODEL_PIXEL_SCALE: u16 = 33550;
const MODEL_TIEPOINT: u16 = 33922;
const GEO_KEY_DIRECTORY: u16 = 34735;
const GDAL_NODATA: u16 = 42113;

/// Where a raster lies in its CRS, when its file says: the CRS, the north-west corner and
/// the pixel size in CRS units.
pub fn crs_placement(
    georeference: Option<&Georeference>,
    pixel: Option<(f64, f64)>,
) -> Option<(&str, [f64; 2], (f64, f64))> {
    let g = georeference?;
    Some((g.crs.as_deref()?, g.origin?, pixel?))
}

/// The GeoTIFF tags that place a raster on the Earth.
pub(super) struct GeoTags {
    scale: Option<Vec<f64>>,
    tiepoint: Option<Vec<f64>>,
    keys: Option<Vec<f64>>,
}

impl GeoTags {
    pub(super) fn read<R: std::io::Read + std::io::Seek>(decoder: &mut tiff::decoder::Decoder<R>) -> Self {
        use tiff::tags::Tag;
        let mut tag = |t: u16| -> Option<Vec<f64>> { decoder.find_tag(Tag::Unknown(t)).ok()??.into_f64_vec().ok() };
        let scale = tag(MODEL_PIXEL_SCALE);
        let tiepoint = tag(MODEL_TIEPOINT);
        #[expect(clippy::cast_precision_loss, reason = "GeoKey values are u16")]
        let keys: Option<Vec<f64>> = decoder
            .find_tag(Tag::Unknown(GEO_KEY_DIRECTORY))
            .ok()
            .flatten()
            .and_then(|v| v.into_u64_vec().ok())
            .map(|v| v.into_iter().map(|k| k as f64).collect());
        Self { scale, tiepoint, keys }
    }

    /// `VerticalCSTypeGeoKey`: the EPSG code of the heights' vertical CRS, where given.
    pub(super) fn vertical_code(&self) -> Option<u32> {
        let k = self.keys.as_ref()?;
        let v = k.chunks_exact(4).skip(1).find(|e| e[0] == 4096.0 && e[1] == 0.0).map(|e| e[3])?;
        #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "GeoKey values are u16")]
        (v > 0.0 && v < 32767.0).then_some(v as u32)
    }

    /// The pixel scale in CRS units, when it is a usable one.
    pub(super) fn crs_pixel(&self) -> Option<(f64, f64)> {
        let s = self.scale.as_ref()?;
        (s.len() >= 2 && s[0].is_finite() && s[1].is_finite() && s[0] > 0.0 && s[1] > 0.0).then(|| (s[0], s[1]))
    }

    /// Sample spacing in metres (x, y) and the georeference; (1, 1) and none without tags.
    ///
    /// # Errors
    /// [`Error::Georeference`] naming `path` for a pixel scale that is not positive.
    pub(super) fn placement(&self, path: &Path, width: u32, height: u32) -> Result<((f64, f64), Option<Georeference>)> {
        let (scale, tiepoint, keys) = (&self.scale, &self.tiepoint, &self.keys);
        // Georeference: model type 2 = geographic (degrees), else projected (metres assumed).
        let key = |id: f64| -> Option<f64> {
            let k = keys.as_ref()?;
            k.chunks_exact(4).skip(1).find(|e| e[0] == id).map(|e| e[3])
        };
        let geographic = key(1024.0) == Some(2.0);
        let epsg = key(2048.0).or_else(|| key(3072.0)).filter(|&c| c > 0.0 && c < 32767.0);
        let (mut spacing, mut georeference) = ((1.0, 1.0), None);
        if let (Some(s), Some(t)) = (&scale, &tiepoint)
            && s.len() >= 2
            && t.len() >= 6
            && s[0] > 0.0
            && s[1] > 0.0
        {
            // GTRasterTypeGeoKey 2 = PixelIsPoint (SRTM, most DEMs): the tiepoint is a
            // sample's centre, so the raster's corner is half a sample further out (as
            // GDAL reads it).
            let half = if key(1025.0) == Some(2.0) { 0.5 } else { 0.0 };
            let (west, north) = (t[3] - (t[0] + half) * s[0], t[4] + (t[1] + half) * s[1]);
            let g;
            (spacing, g) = georeferenced(
                epsg.map(|c| format!("EPSG:{c}")),
                geographic,
                [west, north],
                (s[0], s[1]),
                (width, height),
            );
            georeference = Some(g);
        }
        if !(spacing.0.is_finite() && spacing.1.is_finite() && spacing.0 > 0.0 && spacing.1 > 0.0) {
            return Err(Error::georeference(path, format!("bad pixel scale {spacing:?}")));
        }
        Ok((spacing, georeference))
    }
}

/// The georeference of a raster of `size` pixels whose north-west corner lies at `origin`
/// in `crs`, pixels `pixel` CRS units apart, and its sample spacing in metres (degrees
/// measured at the centre latitude where the CRS is geographic).
pub(super) fn georeferenced(
    crs: Option<String>,
    geographic: bool,
    [west, north]: [f64; 2],
    pixel: (f64, f64),
    (width, height): (u32, u32),
) -> ((f64, f64), Georeference) {
    let mut g = Georeference { crs, origin: Some([west, north]), ..Georeference::default() };
    let mut spacing = pixel;
    if geographic {
        let (east, south) = (west + pixel.0 * f64::from(width), north - pixel.1 * f64::from(height));
        g.lat_lon_bounds = Some([west, south, east, north]);
        let lat = ((north + south) / 2.0).to_radians();
        spacing = (pixel.0 * 111_320.0 * lat.cos(), pixel.1 * 110_574.0);
    }
    (spacing, g)
}

/// GDAL's metadata tag: XML of `<Item name="..." sample="...">value</Item>`.
const GDAL_METADATA: u16 = 42112;

/// The exact minimum and maximum of band 1 as GDAL records them in its metadata tag
/// (`gdalinfo -stats`, `gdal_translate -stats`); None where there are none, or where GDAL
/// says they are approximate (`STATISTICS_APPROXIMATE=YES`: from overviews or a subset).
pub(super) fn gdal_statistics<R: std::io::Read + std::io::Seek>(
    decoder: &mut tiff::decoder::Decoder<R>,
) -> Option<(f64, f64)> {
    let xml = decoder.find_tag(tiff::tags::Tag::Unknown(GDAL_METADATA)).ok().flatten()?.into_string().ok()?;
    statistics_in(&xml)
}

/// `gdal_statistics` of a GDAL metadata document (the text of the GDAL_METADATA tag):
/// the exact minimum and maximum of band 1, if it records them.
pub fn statistics_in(xml: &str) -> Option<(f64, f64)> {
    let item = |name: &str| -> Option<&str> {
        xml.split("<Item").skip(1).find_map(|item| {
            let (head, rest) = item.split_once('>')?;
            let named = head.contains(&format!("name=\"{name}\""));
            let band_one = !head.contains("sample=") || head.contains("sample=\"0\"");
            let role_free = !head.contains("role=");
            (named && band_one && role_free).then(|| rest.split('<').next().unwrap_or("").trim())
        })
    };
    if item("STATISTICS_APPROXIMATE").is_some_and(|v| v.eq_ignore_ascii_case("YES")) {
        return None;
    }
    let (min, max): (f64, f64) = (item("STATISTICS_MINIMUM")?.parse().ok()?, item("STATISTICS_MAXIMUM")?.parse().ok()?);
    (min.is_finite() && max.is_finite() && min <= max).then_some((min, max))
}

/// The GDAL nodata tag's value, when there is one and it is a number.
pub(super) fn gdal_nodata<R: std::io::Read + std::io::Seek>(decoder: &mut tiff::decoder::Decoder<R>) -> Option<f64> {
    decoder
        .find_tag(tiff::tags::Tag::Unknown(GDAL_NODATA))
        .ok()
        .flatten()
        .and_then(|v| v.into_string().ok())
        .and_then(|s| s.trim_matches(char::from(0)).trim().parse().ok())
}

#[cfg(test)]
mod statistics_tests {
    use super::statistics_in;
    use proptest::prelude::*;

    proptest! {
        /// Any text, and items of any name, band and value: no panic, and what is
        /// accepted is a finite, ordered pair.
        #[test]
        fn any_metadata_reads_without_panic(
            text in ".{0,200}",
            items in proptest::collection::vec(
                (prop_oneof!["STATISTICS_MINIMUM", "STATISTICS_MAXIMUM", "STATISTICS_APPROXIMATE", ".{0,12}"],
                 prop_oneof!["0", "1", ".{0,3}"], prop_oneof!["-?[0-9]{1,6}(\\.[0-9]{0,4})?", "YES", "inf", "NaN", ".{0,8}"]),
                0..6),
        ) {
            let mut xml = format!("<GDALMetadata>{text}");
            for (name, sample, value) in &items {
                xml.push_str(&format!("<Item name=\"{name}\" sample=\"{sample}\">{value}</Item>"));
            }
            if let Some((min, max)) = statistics_in(&xml) {
                prop_assert!(min.is_finite() && max.is_finite() && min <= max);
            }
        }
    }

    #[test]
    fn gdal_statistics_are_read_unless_approximate_or_of_another_band() {
        let doc = |items: &str| format!("<GDALMetadata>\n{items}\n</GDALMetadata>\n");
        let exact = doc(r#"<Item name="STATISTICS_MAXIMUM" sample="0">812.5</Item>
  <Item name="STATISTICS_MEAN" sample="0">300</Item>
  <Item name="STATISTICS_MINIMUM" sample="0">-3</Item>"#);
        assert_eq!(statistics_in(&exact), Some((-3.0, 812.5)));
        let approximate = doc(r#"<Item name="STATISTICS_APPROXIMATE" sample="0">YES</Item>
  <Item name="STATISTICS_MAXIMUM" sample="0">812.5</Item><Item name="STATISTICS_MINIMUM" sample="0">-3</Item>"#);
        assert_eq!(statistics_in(&approximate), None);
        let other_band = doc(r#"<Item name="STATISTICS_MAXIMUM" sample="1">9</Item>
  <Item name="STATISTICS_MINIMUM" sample="1">1</Item>"#);
        assert_eq!(statistics_in(&other_band), None);
        assert_eq!(statistics_in(&doc(r#"<Item name="STATISTICS_MINIMUM" sample="0">5</Item>"#)), None);
        let backwards = doc(r#"<Item name="STATISTICS_MAXIMUM" sample="0">1</Item>
  <Item name="STATISTICS_MINIMUM" sample="0">5</Item>"#);
        assert_eq!(statistics_in(&backwards), None);
    }
}
