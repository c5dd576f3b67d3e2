//! Elevation and imagery in different CRSs line up: a DEM in EPSG:4326 and an image of the
//! same place in UTM zone 33N, made from a geographic image by GDAL's `gdalwarp` (Debian
//! `gdal-bin`, the independent oracle), with a red mark painted at a known longitude and
//! latitude. After tiling, the mark lies on the texel where that longitude and latitude
//! lie, within one texel; the unwarped image is refused, never stretched.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::cast_possible_truncation,
    clippy::cast_sign_loss,
    missing_docs
)]

mod common;

use std::path::Path;
use std::process::Command;

use terrastream_format::{LayerKind, Reader, TileKey};
use terrastream_pack::progress::Silent;
use terrastream_tiler::{
    Crs, ElevationSource, ImageSource, Mosaic, MosaicOptions, Pixels, TextureFormat, TextureInput, TileOptions, Warped,
    open_elevation, open_image, tile_terrain,
};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

/// The DEM: west, north, degrees per sample, samples across and down.
const DEM: (f64, f64, f64, u32, u32) = (12.40, 45.48, 0.0005, 240, 160);
/// The source image (wider than the DEM; pixels of about 4 x 5.5 m, so that GDAL's own
/// resampling to 15 m moves the mark by well under a texel): west, north, degrees per
/// pixel, size.
const IMAGE: (f64, f64, f64, u32, u32) = (12.39, 45.49, 0.00005, 2800, 1900);
/// The mark's longitude and latitude.
const MARK: (f64, f64) = (12.4637, 45.4419);

fn geotiff_tags(
    image: &mut tiff::encoder::DirectoryEncoder<'_, std::fs::File, tiff::encoder::TiffKindStandard>,
    west: f64,
    north: f64,
    step: f64,
) {
    image.write_tag(Tag::Unknown(33550), &[step, step, 0.0][..]).unwrap();
    image.write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, west, north, 0.0][..]).unwrap();
    image.write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326][..]).unwrap();
}

fn write_dem(path: &Path) {
    let (west, north, step, w, h) = DEM;
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::Gray32Float>(w, h).unwrap();
    geotiff_tags(image.encoder(), west, north, step);
    let data: Vec<f32> =
        (0..h).flat_map(|j| (0..w).map(move |i| 10.0 + (i as f32 * 0.05).sin() * 20.0 + j as f32 * 0.3)).collect();
    image.write_data(&data).unwrap();
}

fn write_marked_image(path: &Path) {
    let (west, north, step, w, h) = IMAGE;
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<colortype::RGB8>(w, h).unwrap();
    geotiff_tags(image.encoder(), west, north, step);
    let (mi, mj) = ((MARK.0 - west) / step, (north - MARK.1) / step);
    let data: Vec<u8> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .flat_map(|(i, j)| {
            let near = (f64::from(i) + 0.5 - mi).abs() <= 12.0 && (f64::from(j) + 0.5 - mj).abs() <= 12.0;
            if near { [255, 0, 0] } else { [60, 90 + (i % 50) as u8, 60 + (j % 50) as u8] }
        })
        .collect();
    image.write_data(&data).unwrap();
}

fn gdalwarp() -> bool {
    common::tool("gdalwarp", "gdal-bin")
}

#[test]
fn an_image_in_another_crs_is_placed_by_its_georeference() {
    if !gdalwarp() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (dem, geographic, utm, out) = (
        dir.path().join("dem.tif"),
        dir.path().join("image-4326.tif"),
        dir.path().join("image-32633.tif"),
        dir.path().join("t.tspack"),
    );
    write_dem(&dem);
    write_marked_image(&geographic);
    let status = Command::new("gdalwarp")
        .args(["-q", "-t_srs", "EPSG:32633", "-r", "bilinear", "-tr", "15", "15"])
        .arg(&geographic)
        .arg(&utm)
        .status()
        .unwrap();
    assert!(status.success(), "gdalwarp failed");

    let elevation = open_elevation(&dem, None).unwrap();
    let image = open_image(&utm).unwrap();
    assert_eq!(image.georeference().and_then(|g| g.crs.as_deref()), Some("EPSG:32633"));
    // Not warped: refused, naming the image, instead of stretched over the DEM.
    let raw = TextureInput { source: &image, tile_size: 128, format: TextureFormat::Png, pixel_size: 1.0 };
    let err =
        tile_terrain(Some(&elevation), Some(raw), "t", &out, TileOptions::default(), &Silent::default()).unwrap_err();
    assert!(err.to_string().contains("image-32633.tif") && err.to_string().contains("EPSG:32633"), "{err}");
    assert!(!out.exists());

    let warped = Warped::over(&elevation, &image).unwrap().expect("different CRSs: warped");
    let texture = TextureInput { source: &warped, tile_size: 128, format: TextureFormat::Png, pixel_size: 1.0 };
    tile_terrain(Some(&elevation), Some(texture), "t", &out, TileOptions::default(), &Silent::default()).unwrap();

    let th = warped.size().1;
    let off = mark_offset(&out, &elevation, th);
    eprintln!("the mark lies {off:.2} texels from its longitude and latitude");
    assert!(off <= 1.0, "the mark lies {off:.2} texels from its longitude and latitude");

    // The same image moved 50 km east lies nowhere over the DEM: refused, naming it.
    let far = dir.path().join("image-far.tif");
    let status = Command::new("gdal_translate")
        .args(["-q", "-a_ullr"])
        .args(utm_bounds_shifted(&utm, 50_000.0))
        .arg(&utm)
        .arg(&far)
        .status()
        .unwrap();
    assert!(status.success(), "gdal_translate failed");
    let image = open_image(&far).unwrap();
    let Err(err) = Warped::over(&elevation, &image) else { panic!("no overlap: refused") };
    assert!(err.to_string().contains("image-far.tif") && err.to_string().contains("nowhere over"), "{err}");
}

/// `ulx uly lrx lry` of a GeoTIFF (from `gdalinfo -json`), moved `east` metres.
fn utm_bounds_shifted(path: &Path, east: f64) -> Vec<String> {
    let out = Command::new("gdalinfo").arg("-json").arg(path).output().unwrap();
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let corner = |name: &str, i: usize| info["cornerCoordinates"][name][i].as_f64().unwrap();
    [corner("upperLeft", 0) + east, corner("upperLeft", 1), corner("lowerRight", 0) + east, corner("lowerRight", 1)]
        .iter()
        .map(ToString::to_string)
        .collect()
}

/// How far (in texels) the red mark's centroid in the texture of the archive at `out`
/// lies from the texel of its longitude and latitude, for a texture `th` texels tall over
/// `elevation`.
fn mark_offset(out: &Path, elevation: &dyn ElevationSource, th: u32) -> f64 {
    // Where the red texels are, in texels of LOD 0 of the texture layer.
    let reader = Reader::open_mmap(out).unwrap();
    let meta = reader.metadata();
    let index = meta.layers.iter().position(|l| l.kind == LayerKind::Texture).unwrap();
    let layer = &meta.layers[index];
    let res = layer.tile_resolution;
    let (mut sum, mut n) = ((0.0, 0.0), 0.0);
    for ty in 0..layer.num_y_tiles {
        for tx in 0..layer.num_x_tiles {
            let Some(png) = reader.tile(TileKey::new(index as u8, 0, tx, ty).unwrap()).unwrap() else { continue };
            let mut decoder = png::Decoder::new(std::io::Cursor::new(png.to_vec()));
            decoder.set_transformations(png::Transformations::EXPAND);
            let mut r = decoder.read_info().unwrap();
            let mut buf = vec![0; r.output_buffer_size().unwrap()];
            let info = r.next_frame(&mut buf).unwrap();
            let channels = info.color_type.samples();
            // Tiles carry a border of `layer.border` texels on each side.
            let (edge, border) = (info.width, u32::from(layer.border));
            for j in 0..res {
                for i in 0..res {
                    let p = &buf[(((j + border) * edge + i + border) as usize) * channels..][..3];
                    if p[0] > 200 && p[1] < 60 && p[2] < 60 {
                        sum.0 += f64::from(tx * res + i) + 0.5;
                        sum.1 += f64::from(ty * res + j) + 0.5;
                        n += 1.0;
                    }
                }
            }
        }
    }
    assert!(n > 0.0, "the mark is not in the texture");
    let found = (sum.0 / n, sum.1 / n);
    // The texture spans the DEM's extent, linear in longitude and latitude.
    let (west, north, step, w, h) = DEM;
    // The tiler squares samples and texels in metres: the elevation is resampled along x
    // to `w * sx / sy` samples, the texture to the same aspect.
    let (sx, sy) = elevation.spacing();
    let squared = (f64::from(w) * sx / sy).round();
    let tw = (f64::from(th) * squared / f64::from(h)).round() as u32;
    let expected = (
        (MARK.0 - west) / (step * f64::from(w)) * f64::from(tw),
        (north - MARK.1) / (step * f64::from(h)) * f64::from(th),
    );
    eprintln!("the mark lies at texel {found:?}, its longitude and latitude at {expected:?}");
    ((found.0 - expected.0).powi(2) + (found.1 - expected.1).powi(2)).sqrt()
}

#[test]
fn a_mosaic_of_images_in_two_crss_lines_up() {
    if !gdalwarp() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (dem, geographic, out) =
        (dir.path().join("dem.tif"), dir.path().join("image-4326.tif"), dir.path().join("m.tspack"));
    write_dem(&dem);
    write_marked_image(&geographic);
    // The image cut in two overlapping halves, the mark on the seam; the west half warped
    // to UTM 32N, the east half to UTM 33N.
    let (west, east) = (dir.path().join("west-32632.tif"), dir.path().join("east-32633.tif"));
    for (path, window, zone) in
        [(&west, ["0", "0", "1480", "1900"], "EPSG:32632"), (&east, ["1460", "0", "1340", "1900"], "EPSG:32633")]
    {
        let cut = dir.path().join("cut.tif");
        let ok = Command::new("gdal_translate")
            .arg("-q")
            .arg("-srcwin")
            .args(window)
            .arg(&geographic)
            .arg(&cut)
            .status()
            .unwrap();
        assert!(ok.success());
        let ok = Command::new("gdalwarp")
            .args([
                "-q",
                "-overwrite",
                "-t_srs",
                zone,
                "-r",
                "bilinear",
                "-tr",
                "15",
                "15",
                "-dstalpha",
                "-co",
                "TILED=YES",
            ])
            .arg(&cut)
            .arg(path)
            .status()
            .unwrap();
        assert!(ok.success());
    }
    let elevation = open_elevation(&dem, None).unwrap();
    let g = elevation.georeference().unwrap();
    let (origin, (px, py), (w, h)) = (g.origin.unwrap(), elevation.crs_pixel_size().unwrap(), elevation.size());
    let extent = [origin[0], origin[1] - f64::from(h) * py, origin[0] + f64::from(w) * px, origin[1]];
    let options =
        MosaicOptions { crs: Some(Crs::epsg(4326).unwrap()), extent: Some(extent), ..MosaicOptions::default() };
    let mosaic = Mosaic::<Pixels>::open(&[west, east], &options).unwrap();
    let texture = TextureInput { source: &mosaic, tile_size: 128, format: TextureFormat::Png, pixel_size: 1.0 };
    tile_terrain(Some(&elevation), Some(texture), "m", &out, TileOptions::default(), &Silent::default()).unwrap();
    let off = mark_offset(&out, &elevation, ImageSource::size(&mosaic).1);
    eprintln!("the mark lies {off:.2} texels from its longitude and latitude");
    assert!(off <= 1.0, "the mark lies {off:.2} texels from its longitude and latitude");
}

/// Runs a GDAL tool, which must succeed.
fn gdal(tool: &str, args: &[&str], paths: &[&Path]) {
    let ok = Command::new(tool).args(args).args(paths).status().unwrap();
    assert!(ok.success(), "{tool} {args:?} failed");
}

/// Rows of an image source, as RGBA.
fn pixels_of(source: &dyn ImageSource) -> Vec<[u8; 4]> {
    let mut out = Vec::new();
    source
        .rows(&mut |row| {
            out.extend_from_slice(row);
            Ok(())
        })
        .unwrap();
    out
}

#[test]
fn png_and_jpeg_are_placed_by_their_world_files() {
    if !gdalwarp() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name);
    write_dem(&p("dem.tif"));
    write_marked_image(&p("image-4326.tif"));
    // The west half warped to UTM 32N, the east half to UTM 33N (the mark on the seam),
    // each as a GeoTIFF and as a PNG with a world file and GDAL's .aux.xml (its CRS).
    for (name, window, zone) in
        [("west", ["0", "0", "1480", "1900"], "EPSG:32632"), ("east", ["1460", "0", "1340", "1900"], "EPSG:32633")]
    {
        let mut args = vec!["-q", "-srcwin"];
        args.extend(window);
        gdal("gdal_translate", &args, &[&p("image-4326.tif"), &p("cut.tif")]);
        let warp = ["-q", "-overwrite", "-t_srs", zone, "-r", "bilinear", "-tr", "15", "15", "-dstalpha"];
        gdal("gdalwarp", &warp, &[&p("cut.tif"), &p(&format!("{name}.tif"))]);
        let png = ["-q", "-of", "PNG", "-co", "WORLDFILE=YES"];
        gdal("gdal_translate", &png, &[&p(&format!("{name}.tif")), &p(&format!("{name}.png"))]);
        assert!(p(&format!("{name}.wld")).is_file() && p(&format!("{name}.png.aux.xml")).is_file());
    }
    let elevation = open_elevation(&p("dem.tif"), None).unwrap();
    let g = elevation.georeference().unwrap();
    let (origin, (px, py), (w, h)) = (g.origin.unwrap(), elevation.crs_pixel_size().unwrap(), elevation.size());
    let extent = [origin[0], origin[1] - f64::from(h) * py, origin[0] + f64::from(w) * px, origin[1]];
    let options =
        MosaicOptions { crs: Some(Crs::epsg(4326).unwrap()), extent: Some(extent), ..MosaicOptions::default() };

    // PNGs placed by their world files make the very pixels the GeoTIFFs make: the world
    // file's pixel centre is half a pixel inside the GeoTIFF's corner.
    let tiffs = Mosaic::<Pixels>::open(&[p("west.tif"), p("east.tif")], &options).unwrap();
    let pngs = Mosaic::<Pixels>::open(&[p("west.png"), p("east.png")], &options).unwrap();
    let (a, b) = (pixels_of(&tiffs), pixels_of(&pngs));
    assert!(a.iter().filter(|px| px[3] > 0).count() > a.len() / 2, "the mosaic has data");
    assert!(a == b, "the PNG mosaic differs from the GeoTIFF mosaic");
    // A VRT of imagery has a band per colour (RGBA here), each reading that band of the
    // same sources: it is the mosaic of its sources (one here: gdalbuildvrt takes one CRS).
    // One that mixes bands is refused.
    let mut build = Command::new("gdalbuildvrt");
    build.args(["-q", "-srcnodata", "None"]).arg(p("both.vrt")).arg(p("west.tif"));
    assert!(build.status().unwrap().success());
    let (vrt, west) =
        (Mosaic::<Pixels>::open(&[p("both.vrt")], &options), Mosaic::<Pixels>::open(&[p("west.tif")], &options));
    assert!(pixels_of(&vrt.unwrap()) == pixels_of(&west.unwrap()), "the VRT's mosaic differs from its source's");
    let text = std::fs::read_to_string(p("both.vrt")).unwrap();
    let swapped = text.replacen("<SourceBand>2</SourceBand>", "<SourceBand>3</SourceBand>", 1);
    assert_ne!(swapped, text);
    std::fs::write(p("swapped.vrt"), swapped).unwrap();
    let err = Mosaic::<Pixels>::open(&[p("swapped.vrt")], &options).unwrap_err().to_string();
    assert!(err.contains("swapped.vrt") && err.contains("band 2"), "{err}");
    // A TIFF without GeoTIFF tags, placed by a .tfw and GDAL's .aux.xml, lies where the
    // GeoTIFF does.
    let baseline = ["-q", "-co", "PROFILE=BASELINE", "-co", "TFW=YES"];
    gdal("gdal_translate", &baseline, &[&p("east.tif"), &p("plain.tif")]);
    assert!(p("plain.tfw").is_file());
    let (geo, plain) = (open_image(&p("east.tif")).unwrap(), open_image(&p("plain.tif")).unwrap());
    assert_eq!(plain.georeference().and_then(|g| g.crs.as_deref()), Some("EPSG:32633"));
    let (o, q) = (geo.georeference().unwrap().origin.unwrap(), plain.georeference().unwrap().origin.unwrap());
    assert!((o[0] - q[0]).abs() < 1e-6 && (o[1] - q[1]).abs() < 1e-6, "{o:?} against {q:?}");
    assert_eq!(geo.crs_pixel_size(), plain.crs_pixel_size());

    // The west half as a JPEG (no alpha: it comes first, the PNG with alpha wins over it),
    // its world file a .jgw and its CRS an ESRI .prj instead of GDAL's .aux.xml.
    let jpeg = ["-q", "-of", "JPEG", "-b", "1", "-b", "2", "-b", "3", "-co", "WORLDFILE=YES", "-co", "QUALITY=95"];
    gdal("gdal_translate", &jpeg, &[&p("west.tif"), &p("west.jpg")]);
    std::fs::rename(p("west.wld"), p("west.jgw")).unwrap();
    std::fs::remove_file(p("west.jpg.aux.xml")).unwrap();
    // Without a CRS beside it, the world file alone is refused, naming it.
    let err = open_image(&p("west.jpg")).unwrap_err().to_string();
    assert!(err.contains("west.jgw") && err.contains("west.prj"), "{err}");
    let esri = Command::new("gdalsrsinfo").args(["-o", "wkt_esri", "EPSG:32632"]).output().unwrap();
    assert!(esri.status.success());
    std::fs::write(p("west.prj"), &esri.stdout).unwrap();
    let image = open_image(&p("west.jpg")).unwrap();
    assert_eq!(image.georeference().and_then(|g| g.crs.as_deref()), Some("EPSG:32632"));

    let mosaic = Mosaic::<Pixels>::open(&[p("west.jpg"), p("east.png")], &options).unwrap();
    let out = p("m.tspack");
    let texture = TextureInput { source: &mosaic, tile_size: 128, format: TextureFormat::Png, pixel_size: 1.0 };
    tile_terrain(Some(&elevation), Some(texture), "m", &out, TileOptions::default(), &Silent::default()).unwrap();
    let off = mark_offset(&out, &elevation, ImageSource::size(&mosaic).1);
    eprintln!("the mark lies {off:.2} texels from its longitude and latitude");
    assert!(off <= 1.0, "the mark lies {off:.2} texels from its longitude and latitude");

    // One PNG in another CRS than the DEM: refused unwarped, placed when warped.
    let image = open_image(&p("east.png")).unwrap();
    let raw = TextureInput { source: &image, tile_size: 128, format: TextureFormat::Png, pixel_size: 1.0 };
    let one = p("one.tspack");
    let err =
        tile_terrain(Some(&elevation), Some(raw), "t", &one, TileOptions::default(), &Silent::default()).unwrap_err();
    assert!(err.to_string().contains("east.png") && err.to_string().contains("EPSG:32633"), "{err}");
    assert!(Warped::over(&elevation, &image).unwrap().is_some(), "different CRSs: warped");
}
