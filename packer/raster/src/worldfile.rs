//! Where a PNG or JPEG lies, from the files GIS tools write beside it: a world file
//! (`.pgw`, `.jgw`, `.pngw`, `.wld`, …: pixel size, rotation and the centre of the
//! north-west pixel) or a GDAL `.aux.xml` with a `<GeoTransform>`, and the CRS from a
//! `.prj` (WKT, GDAL's or ESRI's) or the `.aux.xml`'s `<SRS>`.
//!
//! A placement without a CRS is refused rather than guessed: the same numbers mean
//! metres in one CRS and degrees in another.

use std::path::{Path, PathBuf};

use terrastream_format::Georeference;

use super::geotiff::georeferenced;
use crate::crs::{Crs, crs_of_srs};
use crate::error::{Error, Result};

/// What the files beside an image say of it.
#[derive(Clone, Debug)]
pub(super) struct Sidecar {
    /// Sample spacing in metres (x, y).
    pub spacing: (f64, f64),
    /// Where the image lies.
    pub georeference: Georeference,
    /// A pixel's size in CRS units (x, y).
    pub crs_pixel: (f64, f64),
}

/// The world file beside `image`, named as GIS tools name it: the extension's first and
/// last letters and `w` (`.jgw`, `.pgw`), the extension and `w` (`.jpgw`), or `.wld`; in
/// lower or upper case.
pub(super) fn world_file(image: &Path) -> Option<PathBuf> {
    let ext = image.extension()?.to_str()?;
    let (first, last) = (ext.chars().next()?, ext.chars().last()?);
    [format!("{first}{last}w"), format!("{ext}w"), "wld".to_owned()]
        .into_iter()
        .flat_map(|e| [e.to_ascii_lowercase(), e.to_ascii_uppercase()])
        .map(|e| image.with_extension(e))
        .find(|p| p.is_file())
}

/// Where `image` (`size` pixels) lies by the files beside it; `None` when no world file
/// or `.aux.xml` places it.
///
/// # Errors
/// [`Error::Georeference`] naming the file at fault: a world file that is not six numbers, a
/// rotated, sheared or south-up grid, a placement with no CRS beside it, a CRS that
/// names nothing the tiler knows.
pub(super) fn read_sidecar(image: &Path, size: (u32, u32)) -> Result<Option<Sidecar>> {
    let aux = aux_xml(image)?;
    let (placed_by, transform) = match world_file(image) {
        Some(world) => {
            let text = std::fs::read_to_string(&world).map_err(|e| Error::file(&world, e))?;
            let numbers: Vec<f64> = text
                .split_whitespace()
                .map(str::parse)
                .collect::<std::result::Result<_, _>>()
                .map_err(|e| Error::georeference(&world, format!("not a world file (six numbers): {e}")))?;
            let [a, d, b, e, c, f] = numbers[..] else {
                return Err(Error::georeference(
                    &world,
                    format!("not a world file: {} numbers, six expected", numbers.len()),
                ));
            };
            // World files give the centre of the north-west pixel; GDAL's transform the corner.
            (world, [c - a / 2.0 - b / 2.0, a, b, f - d / 2.0 - e / 2.0, d, e])
        }
        None => match aux.as_ref().and_then(|a| a.transform.map(|t| (a.path.clone(), t))) {
            Some(found) => found,
            None => return Ok(None),
        },
    };
    let [west, a, b, north, d, e] = transform;
    let bad = |why: String| Error::georeference(&placed_by, why);
    if transform.iter().any(|v| !v.is_finite()) {
        return Err(bad("a placement that is not finite".into()));
    }
    if b != 0.0 || d != 0.0 {
        return Err(bad(format!(
            "a rotated or sheared grid (rotation terms {d}, {b}): only north-up images are read; warp it first \
             (gdalwarp)"
        )));
    }
    if a <= 0.0 || e >= 0.0 {
        return Err(bad(format!("pixel sizes {a} x {e}: only north-up images (x size > 0, y size < 0) are read")));
    }
    let (crs_file, srs) = match (aux.and_then(|a| a.srs.map(|s| (a.path, s))), prj(image)) {
        (Some(found), _) => found,
        (None, Some(prj)) => {
            let text = std::fs::read_to_string(&prj).map_err(|e| Error::file(&prj, e))?;
            (prj, text)
        }
        (None, None) => {
            return Err(bad(format!(
                "it places {} but nothing beside it says in which CRS: add {} holding the CRS as WKT (gdalsrsinfo \
                 -o wkt_esri EPSG:<code>)",
                image.display(),
                image.with_extension("prj").display()
            )));
        }
    };
    let name = crs_of_srs(&srs).ok_or_else(|| {
        Error::georeference(&crs_file, format!("names no CRS the tiler knows (no EPSG code): {:.80}", srs.trim()))
    })?;
    let crs = Crs::parse(&name).map_err(|e| Error::georeference(&crs_file, e.to_string()))?;
    let pixel = (a, -e);
    let (spacing, georeference) = georeferenced(Some(crs.name()), crs.is_geographic(), [west, north], pixel, size);
    Ok(Some(Sidecar { spacing, georeference, crs_pixel: pixel }))
}

/// The `.prj` beside `image`, in lower or upper case.
fn prj(image: &Path) -> Option<PathBuf> {
    ["prj", "PRJ"].into_iter().map(|e| image.with_extension(e)).find(|p| p.is_file())
}

/// GDAL's `<image>.aux.xml`: its path, `<SRS>` and `<GeoTransform>` (GDAL's order: west,
/// x size, rotation, north, rotation, y size).
struct AuxXml {
    path: PathBuf,
    srs: Option<String>,
    transform: Option<[f64; 6]>,
}

fn aux_xml(image: &Path) -> Result<Option<AuxXml>> {
    let mut name = image.as_os_str().to_owned();
    name.push(".aux.xml");
    let path = PathBuf::from(name);
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).map_err(|e| Error::file(&path, e))?;
    let doc = roxmltree::Document::parse(&text).map_err(|error| Error::Xml {
        path: path.clone(),
        what: "not GDAL's .aux.xml",
        error,
    })?;
    let root = doc.root_element();
    let child = |name: &str| root.children().find(|c| c.has_tag_name(name)).and_then(|n| n.text());
    let srs = child("SRS").map(str::to_owned).filter(|s| !s.trim().is_empty());
    let transform = child("GeoTransform").map(|t| parse_geotransform(&path, t)).transpose()?;
    Ok(Some(AuxXml { path, srs, transform }))
}

/// The six numbers of a GDAL `<GeoTransform>` (in a VRT or an `.aux.xml`), in GDAL's
/// order.
///
/// # Errors
/// [`Error::Georeference`] naming `path` when they are not six numbers.
pub(super) fn parse_geotransform(path: &Path, text: &str) -> Result<[f64; 6]> {
    let v: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| Error::georeference(path, format!("<GeoTransform>: {e}")))?;
    v.try_into()
        .map_err(|v: Vec<f64>| Error::georeference(path, format!("<GeoTransform> has {} numbers, 6 expected", v.len())))
}

#[cfg(test)]
mod tests {
    use super::{read_sidecar, world_file};

    const UTM_10N: &str = r#"PROJCS["WGS_1984_UTM_Zone_10N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984"]]]"#;

    #[test]
    fn a_world_file_places_the_image_by_its_corner() {
        let dir = tempfile::tempdir().unwrap();
        let image = dir.path().join("a.JPG");
        std::fs::write(&image, b"").unwrap();
        assert!(read_sidecar(&image, (100, 50)).unwrap().is_none());
        // Pixel centres: the north-west one at (500 010, 4 200 000), 20 m apart.
        std::fs::write(dir.path().join("a.JGW"), "20.0\n0\n0\n-20.0\n500010.0\n4200000.0\n").unwrap();
        assert_eq!(world_file(&image), Some(dir.path().join("a.JGW")));
        let err = read_sidecar(&image, (100, 50)).unwrap_err().to_string();
        assert!(err.contains("a.JGW") && err.contains("a.prj"), "{err}");
        std::fs::write(dir.path().join("a.prj"), UTM_10N).unwrap();
        let s = read_sidecar(&image, (100, 50)).unwrap().unwrap();
        assert_eq!(s.georeference.crs.as_deref(), Some("EPSG:32610"));
        assert_eq!(s.georeference.origin, Some([500_000.0, 4_200_010.0]));
        assert_eq!((s.crs_pixel, s.spacing), ((20.0, 20.0), (20.0, 20.0)));
    }

    #[test]
    fn bad_sidecars_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let image = dir.path().join("b.png");
        std::fs::write(&image, b"").unwrap();
        std::fs::write(dir.path().join("b.prj"), UTM_10N).unwrap();
        let world = dir.path().join("b.pgw");
        for (text, why) in [
            ("1\n0\n0\n-1\n5\n", "5 numbers"),
            ("1\n0\nx\n-1\n5\n6\n", "six numbers"),
            ("1\n0.1\n0\n-1\n5\n6\n", "rotated"),
            ("1\n0\n0\n1\n5\n6\n", "north-up"),
        ] {
            std::fs::write(&world, text).unwrap();
            let err = read_sidecar(&image, (4, 4)).unwrap_err().to_string();
            assert!(err.contains("b.pgw") && err.contains(why), "{text:?}: {err}");
        }
        std::fs::write(&world, "1\n0\n0\n-1\n5\n6\n").unwrap();
        std::fs::write(dir.path().join("b.prj"), r#"PROJCS["Lambert_Somewhere"]"#).unwrap();
        let err = read_sidecar(&image, (4, 4)).unwrap_err().to_string();
        assert!(err.contains("b.prj") && err.contains("no EPSG code"), "{err}");
    }

    #[test]
    fn gdal_aux_xml_gives_the_crs_and_may_give_the_transform() {
        let dir = tempfile::tempdir().unwrap();
        let image = dir.path().join("c.png");
        std::fs::write(&image, b"").unwrap();
        std::fs::write(
            dir.path().join("c.png.aux.xml"),
            r#"<PAMDataset><SRS dataAxisToSRSAxisMapping="2,1">GEOGCS["WGS 84",AUTHORITY["EPSG","4326"]]</SRS>
            <GeoTransform> 7.0, 0.5, 0, 47.0, 0, -0.25</GeoTransform></PAMDataset>"#,
        )
        .unwrap();
        let s = read_sidecar(&image, (4, 8)).unwrap().unwrap();
        assert_eq!(s.georeference.crs.as_deref(), Some("EPSG:4326"));
        assert_eq!(s.georeference.origin, Some([7.0, 47.0]));
        assert_eq!(s.georeference.lat_lon_bounds, Some([7.0, 45.0, 9.0, 47.0]));
        assert_eq!(s.crs_pixel, (0.5, 0.25));
    }
}
