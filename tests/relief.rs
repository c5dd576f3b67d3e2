//! Maps from the heights: relief tiles against `gdaldem` (GDAL's command-line tool, the
//! definitions they follow) on the same heights, tiles that join without a seam, and the
//! server's routes and TileJSON for them.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::cast_possible_truncation,
    clippy::cast_precision_loss,
    missing_docs
)]

use std::path::Path;
use std::process::Command;

use terrastream_views::relief::{ReliefOptions, Window, aspect, hillshade, slope};

/// The committed DEM the maps are made from.
const DEM: &str = "packer/pack/data/srtm-tamalpais-320-public-domain.tif";

const W: u32 = 48;
const H: u32 = 40;
/// Pixels of 30 m east-west, 20 m north-south (unequal: each axis's own spacing counts).
const RES: (f64, f64) = (30.0, 20.0);

fn gdal() -> bool {
    let missing =
        if Command::new("gdaldem").output().is_ok() { vec![] } else { vec!["gdaldem (apt-get install gdal-bin)"] };
    terrastream_testkit::browser::skip_or_fail("GDALDEM", &missing)
}

/// Hills and a valley, metres.
fn heights() -> Vec<f32> {
    (0..W * H)
        .map(|i| {
            let (x, y) = (f64::from(i % W), f64::from(i / W));
            (300.0 + 80.0 * (x / 7.0).sin() * (y / 5.0).cos() + 2.0 * x - 3.0 * y + 0.05 * x * y) as f32
        })
        .collect()
}

/// `heights` as a float32 GeoTIFF in UTM 10N, north up, `RES` pixels.
fn write_geotiff(path: &Path, heights: &[f32]) {
    use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
    use tiff::tags::Tag;
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<Gray32Float>(W, H).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[RES.0, RES.1, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, 500_000.0, 4_200_000.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32610][..]).unwrap();
    image.write_data(heights).unwrap();
}

/// gdaldem's output as f64 values, row by row.
fn read_values(path: &Path) -> Vec<f64> {
    let mut decoder = tiff::decoder::Decoder::new(std::fs::File::open(path).unwrap()).unwrap();
    match decoder.read_image().unwrap() {
        tiff::decoder::DecodingResult::U8(v) => v.into_iter().map(f64::from).collect(),
        tiff::decoder::DecodingResult::F32(v) => v.into_iter().map(f64::from).collect(),
        other => panic!("unexpected sample type {:?}", std::mem::discriminant(&other)),
    }
}

fn gdaldem(dir: &Path, args: &[&str]) -> Vec<f64> {
    let out = dir.join(format!("{}.tif", args.join("_").replace('-', "")));
    let status = Command::new("gdaldem")
        .args(&args[..1])
        .arg(dir.join("dem.tif"))
        .arg(&out)
        .args(&args[1..])
        .args(["-q", "-of", "GTiff"])
        .status()
        .unwrap();
    assert!(status.success(), "gdaldem {args:?}");
    read_values(&out)
}

/// Every interior pixel's 3 x 3 window.
fn windows(h: &[f32]) -> impl Iterator<Item = (usize, Window)> + '_ {
    (1..H - 1).flat_map(move |r| {
        (1..W - 1).map(move |c| {
            let at = |dr: u32, dc: u32| f64::from(h[((r + dr - 1) * W + (c + dc - 1)) as usize]);
            ((r * W + c) as usize, std::array::from_fn(|k| at(k as u32 / 3, k as u32 % 3)))
        })
    })
}

#[test]
fn relief_follows_gdaldem_pixel_for_pixel() {
    if !gdal() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let h = heights();
    write_geotiff(&dir.path().join("dem.tif"), &h);
    let defaults = ReliefOptions::default();
    let cases: Vec<(&[&str], ReliefOptions, f64)> = vec![
        (&["hillshade"], defaults.clone(), 0.55),
        (
            &["hillshade", "-z", "3", "-az", "120", "-alt", "30"],
            ReliefOptions { z_factor: 3.0, azimuth: 120.0, altitude: 30.0, ..defaults.clone() },
            0.55,
        ),
        (&["hillshade", "-multidirectional"], ReliefOptions { multidirectional: true, ..defaults.clone() }, 0.55),
    ];
    for (args, options, tolerance) in cases {
        let theirs = gdaldem(dir.path(), args);
        let mut worst: f64 = 0.0;
        for (at, w) in windows(&h) {
            worst = worst.max((hillshade(&w, RES, &options) - theirs[at]).abs());
        }
        eprintln!("gdaldem {args:?}: worst difference {worst:.3}");
        // gdaldem writes bytes: ours rounds to the same byte.
        assert!(worst <= tolerance, "gdaldem {args:?}: worst difference {worst}");
    }
    for (args, percent) in [(&["slope"][..], false), (&["slope", "-p"][..], true)] {
        let theirs = gdaldem(dir.path(), args);
        let worst = windows(&h).map(|(at, w)| (slope(&w, RES, percent) - theirs[at]).abs()).fold(0.0, f64::max);
        eprintln!("gdaldem {args:?}: worst difference {worst:.2e}");
        assert!(worst < 1e-3, "gdaldem {args:?}: worst difference {worst}");
    }
    // Aspect: gdaldem's own Horn form (no spacing: square pixels assumed); gdaldem works
    // in single precision (with an approximate arc tangent): within 0.01 degree.
    let theirs = gdaldem(dir.path(), &["aspect"]);
    let worst = windows(&h).map(|(at, w)| (aspect(&w).unwrap_or(-9999.0) - theirs[at]).abs()).fold(0.0, f64::max);
    eprintln!("gdaldem aspect: worst difference {worst:.2e}");
    assert!(worst < 1e-2, "gdaldem aspect: worst difference {worst}");
}

fn terrastream(args: &[&str], cwd: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(cwd).output().unwrap();
    assert!(out.status.success(), "terrastream {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// The built-in SRTM DEM around Mt Tamalpais, tiled into `work/dem.tspack`.
fn tamalpais(work: &Path) {
    let dem = terrastream_testkit::golden::repo().join(DEM);
    terrastream(&["-q", "tile", "--elevation", dem.to_str().unwrap(), "-o", "dem.tspack"], work);
}

/// The column and row of the web tile of zoom `z` holding a point.
fn tile_at(z: u8, lon: f64, lat: f64) -> (u32, u32) {
    let (columns, rows) = terrastream_views::mercator::tiles_over(z, [lon, lat, lon, lat]);
    (*columns.start(), *rows.start())
}

fn png_gray(path: &Path) -> (u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut data = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut data).unwrap();
    let channels = info.color_type.samples();
    (info.width, data[..info.buffer_size()].chunks_exact(channels).map(|p| p[0]).collect())
}

/// Exported hillshade tiles join without a seam: across every shared edge between two
/// tiles holding data, the step from one tile's last column to the next one's first is no
/// larger than the steps between neighbouring columns inside the tiles. And the server
/// answers the same tiles, with a TileJSON of a `raster` source for them.
#[test]
fn relief_tiles_join_without_a_seam_and_are_served() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    tamalpais(work);
    let args = [
        "-q",
        "export",
        "dem.tspack",
        "--to",
        "xyz",
        "--product",
        "hillshade",
        "--format",
        "png",
        "--size",
        "256",
        "--base-url",
        "https://t/shade",
    ];
    terrastream(&[&args[..], &["--minzoom", "14", "--maxzoom", "14", "-o", "shade"]].concat(), work);
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(work.join("shade/tiles.json")).unwrap()).unwrap();
    assert_eq!(doc["type"], "raster");
    let folder = work.join("shade/14");
    let mut columns: Vec<u32> = std::fs::read_dir(&folder)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_str().unwrap().parse().unwrap())
        .collect();
    columns.sort_unstable();
    let (mut seams, mut inside, mut pairs) = (0.0, 0.0, 0);
    for pair in columns.windows(2).filter(|p| p[1] == p[0] + 1) {
        for entry in std::fs::read_dir(folder.join(pair[0].to_string())).unwrap() {
            let name = entry.unwrap().file_name();
            let east = folder.join(pair[1].to_string()).join(&name);
            if !east.exists() {
                continue;
            }
            let (w, a) = png_gray(&folder.join(pair[0].to_string()).join(&name));
            let (_, b) = png_gray(&east);
            let w = w as usize;
            for row in 0..w {
                let (a1, a2, b0) = (a[row * w + w - 2], a[row * w + w - 1], b[row * w]);
                if a1 > 0 && a2 > 0 && b0 > 0 {
                    seams += f64::from(a2.abs_diff(b0));
                    inside += f64::from(a1.abs_diff(a2));
                    pairs += 1;
                }
            }
        }
    }
    assert!(pairs > 200, "{pairs} pixel pairs across seams");
    let (seam, interior) = (seams / f64::from(pairs), inside / f64::from(pairs));
    eprintln!("mean step across seams {seam:.2}, between the last two columns {interior:.2} ({pairs} rows)");
    assert!(seam <= interior * 1.5 + 0.5, "a seam: {seam:.2} across, {interior:.2} inside");

    // The server: the same tile bytes, a TileJSON of a raster source, 404 off the data.
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &["dem.tspack"], work);
    let (status, body) =
        terrastream_testkit::http::request(server.port, "GET", "/dem/hillshade/tiles.json?size=256", None);
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    let doc: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(doc["type"], "raster");
    assert!(doc["tiles"][0].as_str().unwrap().contains("/dem/xyz/hillshade/{z}/{x}/{y}.webp?size=256"), "{doc}");
    let column = columns[0];
    let row = std::fs::read_dir(folder.join(column.to_string())).unwrap().next().unwrap().unwrap().file_name();
    let row = row.to_str().unwrap().trim_end_matches(".png").to_owned();
    let path = format!("/dem/xyz/hillshade/14/{column}/{row}.png?size=256");
    let (status, served) = terrastream_testkit::http::request(server.port, "GET", &path, None);
    assert_eq!(status, 200);
    assert_eq!(served, std::fs::read(folder.join(column.to_string()).join(format!("{row}.png"))).unwrap());
    for product in ["slope", "aspect", "color-relief"] {
        let (status, body) = terrastream_testkit::http::request(
            server.port,
            "GET",
            &format!("/dem/xyz/{product}/14/{column}/{row}.webp"),
            None,
        );
        assert_eq!(status, 200, "{product}: {}", String::from_utf8_lossy(&body));
        assert!(body.starts_with(b"RIFF"), "{product}: a WebP");
    }
    let (status, body) =
        terrastream_testkit::http::request(server.port, "GET", "/dem/xyz/hillshade/3/1/1.png?altitude=95", None);
    assert_eq!(status, 400, "{}", String::from_utf8_lossy(&body));
    assert_eq!(terrastream_testkit::http::request(server.port, "GET", "/dem/xyz/hillshade/3/0/0.png", None).0, 404);
    // An unknown product: 400 naming it and the products there are.
    for path in ["/dem/xyz/hilshade/14/0/0.png", "/dem/hilshade/tiles.json"] {
        let (status, body) = terrastream_testkit::http::request(server.port, "GET", path, None);
        let text = String::from_utf8_lossy(&body);
        assert_eq!(status, 400, "{path}: {text}");
        assert!(text.contains("\"hilshade\"") && text.contains("hillshade, slope, aspect, color-relief"), "{text}");
    }
}

/// Where a polyline crosses the vertical line `x` (tile units): the crossings' y.
fn crossings(points: &[(i32, i32)], x: i32) -> Vec<f64> {
    let mut out = vec![];
    for pair in points.windows(2) {
        let ((x0, y0), (x1, y1)) = (pair[0], pair[1]);
        if (x0 < x) != (x1 < x) {
            let t = f64::from(x - x0) / f64::from(x1 - x0);
            out.push(f64::from(y0) + t * f64::from(y1 - y0));
        }
    }
    out
}

/// Contour tiles of archives in three CRSs (the default transverse Mercator, geographic
/// degrees and Web Mercator itself): every line crossing an edge between two neighbours,
/// across and down, at zooms 12 and 14, goes on in the other tile from the same point at
/// the same height (within a unit of 4096), whatever the CRS the nodes place it through.
#[test]
fn contour_lines_meet_across_tile_edges_in_every_crs() {
    use terrastream_views::contours::{ContourOptions, contour_tile};
    use terrastream_views::mvt::{Line, decode};
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    let dem = terrastream_testkit::golden::repo().join(DEM);
    let dem = dem.to_str().unwrap();
    terrastream(&["-q", "tile", "--elevation", dem, "-o", "tm.tspack"], work);
    terrastream(&["-q", "tile", "--elevation", dem, "--crs", "EPSG:4326", "-o", "geo.tspack"], work);
    terrastream(&["-q", "tile", "--elevation", dem, "--crs", "EPSG:3857", "-o", "merc.tspack"], work);
    let ele = |l: &Line| l.properties[0].1.number().unwrap_or(f64::NAN);
    // Where a line crosses the edge at `at` along `axis` (0: x = at, 1: y = at).
    let crossing = |l: &Line, axis: usize, at: i32| {
        let swap = |p: (i32, i32)| if axis == 0 { p } else { (p.1, p.0) };
        crossings(&l.points.iter().map(|&p| swap(p)).collect::<Vec<_>>(), at)
    };
    for archive in ["tm.tspack", "geo.tspack", "merc.tspack"] {
        let reader = terrastream_format::Reader::open_mmap(work.join(archive)).unwrap();
        let mut matched = 0;
        for z in [12u8, 14] {
            let (x, y) = tile_at(z, -122.5965, 37.9235);
            let get = |x: u32, y: u32| {
                let tile = terrastream_views::mercator::WebTile::new(z, x, y).unwrap();
                let options = ContourOptions { interval: Some(20.0), ..Default::default() };
                // (A neighbour beyond the data has no tile.)
                contour_tile(&reader, tile, options, None).unwrap().map(|b| decode(&b).unwrap()).unwrap_or_default()
            };
            let here = get(x, y);
            for (axis, there) in [(0, get(x + 1, y)), (1, get(x, y + 1))] {
                if there.is_empty() {
                    continue;
                }
                for line in &here {
                    for along in crossing(line, axis, 4096) {
                        let found = there
                            .iter()
                            .filter(|l| ele(l) == ele(line))
                            .flat_map(|l| crossing(l, axis, 0))
                            .any(|other| (other - along).abs() <= 1.0);
                        assert!(found, "{archive} z{z}: the {} m line leaves at {along:.0} and stops", ele(line));
                        matched += 1;
                    }
                }
            }
        }
        assert!(matched >= 20, "{archive}: {matched} lines cross the edges");
    }
}

/// Contour tiles: a line crossing a tile edge goes on in the neighbour from the same
/// point at the same height (within a unit of 4096: no gap, no kink, none lost); every
/// vertex lies where the terrain has the line's height (the elevation API at the
/// vertex); the TileJSON is a vector source naming its fields; the PMTiles export holds
/// the served tiles.
#[test]
fn contour_lines_continue_across_tile_edges_at_their_heights() {
    use terrastream_views::mvt::decode;
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    tamalpais(work);
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &["dem.tspack"], work);
    let get = |path: &str| terrastream_testkit::http::request(server.port, "GET", path, None);
    let (status, body) = get("/dem/contours/tiles.json?interval=20");
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    let doc: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!((doc["type"].as_str(), doc["vector_layers"][0]["id"].as_str()), (Some("vector"), Some("contours")));
    assert!(doc["tiles"][0].as_str().unwrap().ends_with("/dem/contours/{z}/{x}/{y}.pbf?interval=20"), "{doc}");
    // Zoom 14 over the data's middle: two neighbours side by side.
    let [w, s, e, n]: [f64; 4] = serde_json::from_value(doc["bounds"].clone()).unwrap();
    let (lon, lat) = ((w + e) / 2.0, (s + n) / 2.0);
    let z = 14u8;
    let (x, y) = tile_at(z, lon, lat);
    let k = f64::from(1u32 << z);
    let tile = |x: u32| {
        let (status, body) = get(&format!("/dem/contours/{z}/{x}/{y}.pbf?interval=20"));
        assert_eq!(status, 200);
        decode(&body).unwrap()
    };
    let (west, east) = (tile(x), tile(x + 1));
    let ele = |l: &terrastream_views::mvt::Line| l.properties[0].1.number().unwrap_or(f64::NAN);
    let mut matched = 0;
    for line in &west {
        for y_west in crossings(&line.points, 4096) {
            let found = east
                .iter()
                .filter(|l| ele(l) == ele(line))
                .flat_map(|l| crossings(&l.points, 0))
                .any(|y_east| (y_east - y_west).abs() <= 1.0);
            let near: Vec<f64> =
                east.iter().filter(|l| ele(l) == ele(line)).flat_map(|l| crossings(&l.points, 0)).collect();
            assert!(
                found,
                "the {} m line leaves the west tile at y {y_west:.0} and is not in the east one: {near:?}",
                ele(line)
            );
            matched += 1;
        }
    }
    assert!(matched >= 5, "{matched} lines cross the edge");
    // Every vertex inside the west tile lies at its line's height, within a fifth of the
    // interval (the elevation API's bilinear heights at the vertex).
    let mut points = vec![];
    for line in west.iter().take(40) {
        for &(px, py) in
            line.points.iter().filter(|(px, py)| (0..4096).contains(px) && (0..4096).contains(py)).step_by(7)
        {
            let (fx, fy) = ((f64::from(x) + f64::from(px) / 4096.0) / k, (f64::from(y) + f64::from(py) / 4096.0) / k);
            let lon = fx * 360.0 - 180.0;
            let lat = (std::f64::consts::PI * (1.0 - 2.0 * fy)).sinh().atan().to_degrees();
            points.push((lat, lon, ele(line)));
        }
    }
    assert!(points.len() >= 20, "{} vertices", points.len());
    for chunk in points.chunks(100) {
        let locations: Vec<String> = chunk.iter().map(|(lat, lon, _)| format!("{lat:.7},{lon:.7}")).collect();
        let (status, body) = get(&format!("/v1/dem?locations={}", locations.join("|")));
        assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
        let answer: serde_json::Value = serde_json::from_slice(&body).unwrap();
        for ((_, _, level), result) in chunk.iter().zip(answer["results"].as_array().unwrap()) {
            let h = result["elevation"].as_f64().unwrap();
            assert!((h - level).abs() <= 4.0, "a vertex of the {level} m line lies at {h:.1} m");
        }
    }
    // Bad parameters: 400 naming the parameter.
    for (query, named) in
        [("interval=0", "interval"), ("interval=1e9", "interval"), ("major=0", "major"), ("units=yd", "units")]
    {
        let (status, body) = get(&format!("/dem/contours/{z}/{x}/{y}.pbf?{query}"));
        assert_eq!(status, 400, "{query}");
        assert!(String::from_utf8_lossy(&body).contains(named), "{query}: {}", String::from_utf8_lossy(&body));
    }
    // The PMTiles export: the served tile, byte for byte.
    let zs = z.to_string();
    terrastream(
        &[
            "-q",
            "export",
            "dem.tspack",
            "--to",
            "contours",
            "--interval",
            "20",
            "--minzoom",
            &zs,
            "--maxzoom",
            &zs,
            "-o",
            "c.pmtiles",
        ],
        work,
    );
    let bytes = std::fs::read(work.join("c.pmtiles")).unwrap();
    let (_, served) = get(&format!("/dem/contours/{z}/{x}/{y}.pbf?interval=20"));
    assert!(bytes.windows(served.len()).any(|w| w == served), "the exported tile is the served one");
    assert_eq!(bytes[99], 1, "PMTiles tile type: MVT");
}

/// The server's colour table (`color_relief_table`, gdaldem's format) colours its
/// `color-relief` tiles; a table that is not one stops `serve`, naming the file.
#[test]
fn the_servers_colour_table_colours_its_relief() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    tamalpais(work);
    std::fs::write(work.join("red.txt"), "# everything red\n-500 200 10 20\n9000 200 10 20\nnv 0 0 0 0\n").unwrap();
    std::fs::write(work.join("server.toml"), "color_relief_table = \"red.txt\"\n").unwrap();
    let exe = Path::new(env!("CARGO_BIN_EXE_terrastream"));
    let server = terrastream_testkit::server::spawn_serve(exe, &["dem.tspack", "--config", "server.toml"], work);
    let (status, body) =
        terrastream_testkit::http::request(server.port, "GET", "/dem/color-relief/tiles.json?size=256", None);
    assert_eq!(status, 200);
    let doc: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let [w, s, e, n]: [f64; 4] = serde_json::from_value(doc["bounds"].clone()).unwrap();
    let (x, y) = tile_at(13, (w + e) / 2.0, (s + n) / 2.0);
    let (status, png) = terrastream_testkit::http::request(
        server.port,
        "GET",
        &format!("/dem/xyz/color-relief/13/{x}/{y}.png?size=256"),
        None,
    );
    assert_eq!(status, 200);
    let decoder = png::Decoder::new(std::io::Cursor::new(png));
    let mut reader = decoder.read_info().unwrap();
    let mut data = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut data).unwrap();
    let pixels: Vec<&[u8]> = data[..info.buffer_size()].chunks_exact(info.color_type.samples()).collect();
    let red = pixels.iter().filter(|p| p[..3] == [200, 10, 20]).count();
    assert!(red * 2 > pixels.len(), "{red} of {} pixels in the table's colour", pixels.len());
    drop(server);
    std::fs::write(work.join("bad.txt"), "not a table\n").unwrap();
    std::fs::write(work.join("bad.toml"), "color_relief_table = \"bad.txt\"\n").unwrap();
    let out = Command::new(exe)
        .args(["serve", "dem.tspack", "--config", "bad.toml", "--addr", "127.0.0.1:0"])
        .current_dir(work)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("bad.txt"), "{}", String::from_utf8_lossy(&out.stderr));
}

/// Distance from point `p` to the polyline `line` (tile units).
fn distance_to(p: (f64, f64), line: &[(f64, f64)]) -> f64 {
    line.windows(2)
        .map(|s| {
            let ((x0, y0), (x1, y1)) = (s[0], s[1]);
            let (dx, dy) = (x1 - x0, y1 - y0);
            let t = if dx == 0.0 && dy == 0.0 {
                0.0
            } else {
                (((p.0 - x0) * dx + (p.1 - y0) * dy) / (dx * dx + dy * dy)).clamp(0.0, 1.0)
            };
            (p.0 - x0 - t * dx).hypot(p.1 - y0 - t * dy)
        })
        .fold(f64::INFINITY, f64::min)
}

/// Contour tiles from far out to close in are traced on the archive's own samples, only
/// those under the tile and its buffer that hold data (at zoom 9 the whole archive is 32
/// pixels of the tile), and the summit's rings are there, at the interval's heights.
#[test]
fn contour_tiles_are_traced_on_the_archives_samples_at_every_zoom() {
    use terrastream_views::contours::{ContourOptions, contour_tile, tile_grid};
    use terrastream_views::mvt::decode;
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    tamalpais(work);
    let reader = terrastream_format::Reader::open_mmap(work.join("dem.tspack")).unwrap();
    for z in [9u8, 11, 13, 15] {
        let (x, y) = tile_at(z, -122.5965, 37.9235);
        let tile = terrastream_views::mercator::WebTile::new(z, x, y).unwrap();
        let grid = tile_grid(&reader, tile).unwrap().expect("the summit's tile has data");
        assert!(grid.georeference.is_some(), "zoom {z}: resampled");
        // No more samples than the archive's level holds (320 x 320 at its finest), nor
        // than the tile and its buffer span: 264 pixels at zoom 15 are 44 of its samples.
        assert!(grid.size.0 <= 322 && grid.size.1 <= 322, "zoom {z}: {:?}", grid.size);
        if z == 15 {
            assert!(grid.size.0 < 60 && grid.size.1 < 60, "zoom {z}: {:?}", grid.size);
        }
        let options = ContourOptions { interval: Some(50.0), ..Default::default() };
        let lines = decode(&contour_tile(&reader, tile, options, None).unwrap().unwrap()).unwrap();
        let heights: Vec<f64> = lines.iter().filter_map(|l| l.properties[0].1.number()).collect();
        assert!(!heights.is_empty(), "zoom {z}: no line");
        assert!(heights.iter().all(|h| h % 50.0 == 0.0), "zoom {z}: {heights:?}");
        // Mt Tamalpais' summit is 784 m: a line at 750 m goes round it at every zoom.
        assert!(heights.contains(&750.0), "zoom {z}: {heights:?}");
    }
}

/// The contour tracer against `gdal_contour` on the same samples (the archive's own, under
/// the tile and its margin, in the archive's CRS), gdal's lines taken to Web Mercator by
/// `ogr2ogr`: every line within half a pixel of gdal's line of the same height, both ways
/// (a Hausdorff distance inside the tile), and the same closed rings.
#[test]
fn contours_follow_gdal_contour_on_the_same_grid() {
    use terrastream_views::contours::{tile_grid, trace_grid};
    use terrastream_views::mercator::HALF_WORLD;
    use terrastream_views::mvt::Value;
    let missing = if Command::new("gdal_contour").output().is_ok() && Command::new("ogr2ogr").output().is_ok() {
        vec![]
    } else {
        vec!["gdal_contour and ogr2ogr (apt-get install gdal-bin)"]
    };
    if !terrastream_testkit::browser::skip_or_fail("GDAL_CONTOUR", &missing) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    tamalpais(work);
    let reader = terrastream_format::Reader::open_mmap(work.join("dem.tspack")).unwrap();
    // Zoom 14 at Mt Tamalpais' summit: steep, many rings and lines.
    let (lon, lat, z) = (-122.5965, 37.9235, 14u8);
    let (x, y) = tile_at(z, lon, lat);
    let tile = terrastream_views::mercator::WebTile::new(z, x, y).unwrap();
    let grid = tile_grid(&reader, tile).unwrap().unwrap();
    assert!(grid.heights.iter().all(|h| h.is_finite()), "the tile lies inside the data");
    let (crs, [x0, dx, _, y0, _, dy]) = grid.georeference.clone().expect("traced on the archive's own samples");
    assert!(dx > 0.0 && dy < 0.0, "{dx} {dy}");
    // At zoom 14 the archive's 1" samples are larger than the tile's pixels: fewer of them.
    assert!(grid.size.0 < 256 && grid.size.1 < 256, "{:?}", grid.size);
    // The samples as a GeoTIFF in the archive's CRS coordinates (its CRS given to ogr2ogr).
    {
        use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
        use tiff::tags::Tag;
        let (w, h) = (u32::try_from(grid.size.0).unwrap(), u32::try_from(grid.size.1).unwrap());
        let mut encoder = TiffEncoder::new(std::fs::File::create(work.join("grid.tif")).unwrap()).unwrap();
        let mut image = encoder.new_image::<Gray32Float>(w, h).unwrap();
        image.encoder().write_tag(Tag::Unknown(33550), &[dx, -dy, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, x0, y0, 0.0][..]).unwrap();
        image.write_data(&grid.heights).unwrap();
    }
    let out = Command::new("gdal_contour")
        .args(["-q", "-a", "ele", "-i", "20", "-f", "GeoJSON", "grid.tif", "native.geojson"])
        .current_dir(work)
        .output()
        .unwrap();
    assert!(out.status.success(), "gdal_contour: {}", String::from_utf8_lossy(&out.stderr));
    let out = Command::new("ogr2ogr")
        .args(["-f", "GeoJSON", "-s_srs", &crs, "-t_srs", "EPSG:3857", "gdal.geojson", "native.geojson"])
        .current_dir(work)
        .output()
        .unwrap();
    assert!(out.status.success(), "ogr2ogr: {}", String::from_utf8_lossy(&out.stderr));
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(work.join("gdal.geojson")).unwrap()).unwrap();
    // Web Mercator metres to the tile's units.
    let n = f64::from(1u32 << z);
    let units = |x: f64, y: f64| {
        let (fx, fy) = ((x + HALF_WORLD) / (2.0 * HALF_WORLD), (HALF_WORLD - y) / (2.0 * HALF_WORLD));
        ((fx * n - f64::from(tile.x)) * 4096.0, (fy * n - f64::from(tile.y)) * 4096.0)
    };
    let mut theirs: Vec<(f64, Vec<(f64, f64)>)> = vec![];
    for f in doc["features"].as_array().unwrap() {
        let ele = f["properties"]["ele"].as_f64().unwrap();
        let geometry = &f["geometry"];
        let lines = match geometry["type"].as_str() {
            Some("LineString") => vec![geometry["coordinates"].clone()],
            Some("MultiLineString") => geometry["coordinates"].as_array().unwrap().clone(),
            other => panic!("{other:?}"),
        };
        for line in lines {
            let points = line
                .as_array()
                .unwrap()
                .iter()
                .map(|p| units(p[0].as_f64().unwrap(), p[1].as_f64().unwrap()))
                .collect();
            theirs.push((ele, points));
        }
    }
    let ours: Vec<(f64, Vec<(f64, f64)>)> = trace_grid(&grid, 20.0, 5)
        .into_iter()
        .map(|l| {
            let Value::Number(ele) = l.properties[0].1 else { panic!() };
            (ele, l.points.iter().map(|&(x, y)| (f64::from(x), f64::from(y))).collect())
        })
        .collect();
    let inside = |p: &(f64, f64)| (0.0..=4096.0).contains(&p.0) && (0.0..=4096.0).contains(&p.1);
    let worst = |from: &[(f64, Vec<(f64, f64)>)], to: &[(f64, Vec<(f64, f64)>)]| {
        let mut worst: f64 = 0.0;
        for (ele, line) in from {
            for p in line.iter().filter(|p| inside(p)) {
                let d =
                    to.iter().filter(|(e, _)| e == ele).map(|(_, l)| distance_to(*p, l)).fold(f64::INFINITY, f64::min);
                worst = worst.max(d);
            }
        }
        worst
    };
    let (ours_to_gdal, gdal_to_ours) = (worst(&ours, &theirs), worst(&theirs, &ours));
    eprintln!(
        "{} lines of ours, {} of gdal_contour: Hausdorff {ours_to_gdal:.2} / {gdal_to_ours:.2} units (16 a pixel)",
        ours.len(),
        theirs.len()
    );
    assert!(ours_to_gdal <= 8.0 && gdal_to_ours <= 8.0, "beyond half a pixel: {ours_to_gdal} / {gdal_to_ours}");
    let rings = |lines: &[(f64, Vec<(f64, f64)>)]| {
        let mut r: Vec<f64> = lines
            .iter()
            .filter(|(_, l)| {
                l.len() > 3
                    && l.iter().all(inside)
                    && (l[0].0 - l[l.len() - 1].0).hypot(l[0].1 - l[l.len() - 1].1) < 1.0
            })
            .map(|(e, _)| *e)
            .collect();
        r.sort_by(f64::total_cmp);
        r
    };
    assert_eq!(rings(&ours), rings(&theirs), "closed rings inside the tile, by height");
    assert!(!rings(&ours).is_empty(), "the summit's rings");
}

/// A contour tile read by an independent decoder, npm's `@mapbox/vector-tile` (what
/// MapLibre's own decoder grew from) on `pbf`, under Node.js: version 2, extent 4096,
/// every feature a line string with our vertices, `ele` and `major`.
#[test]
fn contour_tiles_decode_with_mapbox_vector_tile() {
    use terrastream_views::mvt::{Value, decode};
    let npm = std::env::var_os("TERRASTREAM_NPM").map_or_else(
        || std::path::PathBuf::from(std::env::var("HOME").unwrap()).join(".cache/terrastream-npm"),
        Into::into,
    );
    let module = npm.join("node_modules/@mapbox/vector-tile/index.js");
    let mut missing = vec![];
    if !module.exists() {
        missing.push("@mapbox/vector-tile and pbf (scripts/test.sh installs them)");
    }
    if Command::new("node").arg("--version").output().is_err() {
        missing.push("Node.js");
    }
    if !terrastream_testkit::browser::skip_or_fail("VECTOR-TILE", &missing) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    tamalpais(work);
    let reader = terrastream_format::Reader::open_mmap(work.join("dem.tspack")).unwrap();
    // Zoom 13 at Mt Tamalpais' summit.
    let (x, y) = tile_at(13, -122.5965, 37.9235);
    let tile = terrastream_views::mercator::WebTile::new(13, x, y).unwrap();
    let options = terrastream_views::contours::ContourOptions { interval: Some(50.0), ..Default::default() };
    let bytes = terrastream_views::contours::contour_tile(&reader, tile, options, None).unwrap().unwrap();
    std::fs::write(work.join("t.pbf"), &bytes).unwrap();
    let script = format!(
        "import {{ VectorTile }} from {vt:?}; import {{ PbfReader }} from {pbf:?}; import fs from 'fs';
         const tile = new VectorTile(new PbfReader(fs.readFileSync('t.pbf')));
         const layer = tile.layers.contours;
         const features = [];
         for (let i = 0; i < layer.length; i++) {{
           const f = layer.feature(i);
           features.push({{ type: f.type, ele: f.properties.ele, major: f.properties.major,
             lines: f.loadGeometry().map(r => r.map(p => [p.x, p.y])) }});
         }}
         console.log(JSON.stringify({{ names: Object.keys(tile.layers), version: layer.version, extent: layer.extent, features }}));",
        vt = module.display().to_string(),
        pbf = npm.join("node_modules/pbf/index.js").display().to_string()
    );
    std::fs::write(work.join("read.mjs"), script).unwrap();
    let out = Command::new("node").arg("read.mjs").current_dir(work).output().unwrap();
    assert!(out.status.success(), "node: {}", String::from_utf8_lossy(&out.stderr));
    let read: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (read["names"].clone(), read["version"].as_u64(), read["extent"].as_u64()),
        (serde_json::json!(["contours"]), Some(2), Some(4096))
    );
    let ours = decode(&bytes).unwrap();
    let theirs = read["features"].as_array().unwrap();
    assert!(ours.len() >= 5 && ours.len() == theirs.len(), "{} lines, {} read", ours.len(), theirs.len());
    for (line, feature) in ours.iter().zip(theirs) {
        assert_eq!(feature["type"], 2, "a line string");
        let (Value::Number(ele), Value::Bool(major)) = (line.properties[0].1, line.properties[1].1) else { panic!() };
        assert_eq!((feature["ele"].as_f64(), feature["major"].as_bool()), (Some(ele), Some(major)));
        let points: Vec<(i32, i32)> = feature["lines"][0]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| (p[0].as_i64().unwrap() as i32, p[1].as_i64().unwrap() as i32))
            .collect();
        assert_eq!(points, line.points);
    }
}
