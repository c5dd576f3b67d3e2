//! End-to-end tests of the `terrastream` binary: demo, pack, info, verify, extract.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::Path;
use std::process::{Command, Output};

use terrastream_testkit::archives::stored_tiles;
use terrastream_tiler::ElevationSource as _;

fn terrastream(args: &[&str], cwd: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).current_dir(cwd).output().expect("run terrastream")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn demo_then_info_verify_and_extract() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    let out = terrastream(&["demo", "--dir", "demo", "--no-window"], work);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("verify: OK"), "{}", text(&out));
    let archive = work.join("demo/sample.tspack");
    assert!(archive.exists());
    // pack -> serve -> render: the views (a descent on the globe from the whole Earth, and
    // the sample pyramid) were streamed over HTTP and rendered (lavapipe).
    for view in ["earth", "tamalpais-whole", "tamalpais-grazing", "tamalpais-summit", "sample-whole"] {
        let png = work.join(format!("demo/views/{view}.png"));
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&png).unwrap()));
        let info = decoder.read_info().unwrap().info().clone();
        assert_eq!((info.width, info.height), (960, 540), "{}", png.display());
        assert!(text(&out).contains(&format!("{view}.png")), "{}", text(&out));
    }
    assert!(work.join("demo/tamalpais.tspack").exists());

    let out = terrastream(&["info", "demo/sample.tspack", "--json"], work);
    assert!(out.status.success(), "{}", text(&out));
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(doc["stats"]["layers"][0]["tiles_per_lod"], serde_json::json!([47, 12, 4, 1]));
    assert_eq!(doc["metadata"]["terrain"]["displacement"], serde_json::json!(500.0));

    let out = terrastream(&["extract", "demo/sample.tspack", "-o", "back/sample"], work);
    assert!(out.status.success(), "{}", text(&out));
    // Re-packing the extracted tree gives the same archive, byte for byte: pack is
    // deterministic and extract loses nothing.
    let out = terrastream(&["pack", "back/sample", "-o", "again.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    let again = std::fs::read(work.join("again.tspack")).unwrap();
    let first = std::fs::read(&archive).unwrap();
    assert!(again == first, "re-packed archive differs");
    let out = terrastream(&["verify", "again.tspack"], work);
    assert!(out.status.success() && text(&out).contains("OK"), "{}", text(&out));
}

#[test]
fn verify_names_the_damage_and_fails() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    assert!(terrastream(&["demo", "--dir", "d", "--no-window"], work).status.success());
    let path = work.join("d/sample.tspack");
    let mut bytes = std::fs::read(&path).unwrap();
    let n = bytes.len();
    bytes[n - 100] ^= 0x10; // inside the last tile
    std::fs::write(work.join("bad.tspack"), &bytes).unwrap();
    let out = terrastream(&["verify", "bad.tspack"], work);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out));
    assert!(text(&out).contains("checksum mismatch in tile layer"), "{}", text(&out));

    bytes[20] ^= 0x10; // header
    std::fs::write(work.join("bad2.tspack"), &bytes).unwrap();
    let out = terrastream(&["verify", "bad2.tspack"], work);
    assert!(!out.status.success());
    assert!(text(&out).contains("bad2.tspack") && text(&out).contains("header"), "{}", text(&out));

    let out = terrastream(&["info", "missing.tspack"], work);
    assert!(!out.status.success());
    assert!(text(&out).contains("missing.tspack"), "{}", text(&out));
}

#[test]
fn pack_refuses_bad_input_without_writing() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    std::fs::create_dir_all(work.join("in/LOD0")).unwrap();
    std::fs::write(work.join("in/LOD0/0_0.png"), b"not an image").unwrap();
    let out = terrastream(&["pack", "in", "-o", "out.tspack"], work);
    assert!(!out.status.success());
    assert!(text(&out).contains("0_0.png"), "{}", text(&out));
    assert!(!work.join("out.tspack").exists());
    let leftovers: Vec<_> = std::fs::read_dir(work).unwrap().filter_map(|e| e.ok()).map(|e| e.file_name()).collect();
    assert_eq!(leftovers.len(), 1, "only the input folder: {leftovers:?}");
}

/// One HTTP/1.1 request over a plain socket; returns the whole answer.
fn http(port: u16, request: &str) -> Vec<u8> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(request.as_bytes()).unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).unwrap();
    out
}

#[test]
fn pack_then_serve_then_stop_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    assert!(terrastream(&["demo", "--dir", "d", "--no-window"], work).status.success());
    let archive = std::fs::read(work.join("d/sample.tspack")).unwrap();
    let mut server =
        terrastream_testkit::server::spawn_serve(Path::new(env!("CARGO_BIN_EXE_terrastream")), &["d"], work);
    let port = server.port;
    let answer =
        http(port, "GET /sample.tspack HTTP/1.1\r\nHost: x\r\nRange: bytes=0-127\r\nConnection: close\r\n\r\n");
    let head_end = answer.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&answer[..head_end]).to_lowercase();
    assert!(head.starts_with("http/1.1 206"), "{head}");
    assert!(head.contains(&format!("content-range: bytes 0-127/{}", archive.len())), "{head}");
    assert_eq!(&answer[head_end + 4..], &archive[..128]);
    // Every reading command takes the URL: same answers as from the file.
    let url = format!("http://127.0.0.1:{port}/sample.tspack");
    let remote = terrastream(&["info", &url, "--json"], work);
    let local = terrastream(&["info", "d/sample.tspack", "--json"], work);
    assert!(remote.status.success(), "{}", text(&remote));
    let (mut remote, mut local): (serde_json::Value, serde_json::Value) =
        (serde_json::from_slice(&remote.stdout).unwrap(), serde_json::from_slice(&local.stdout).unwrap());
    assert_eq!(remote["stats"].take(), local["stats"].take());
    let exported = terrastream(&["export", &url, "--layer", "texture", "--to", "pmtiles", "-o", "t.pmtiles"], work);
    assert!(exported.status.success(), "{}", text(&exported));
    assert_eq!(&std::fs::read(work.join("t.pmtiles")).unwrap()[..8], b"PMTiles\x03");
    let wrong = terrastream(&["export", &url, "--layer", "normals", "--to", "pmtiles", "-o", "n.pmtiles"], work);
    assert!(!wrong.status.success() && text(&wrong).contains("layers: texture, elevation"), "{}", text(&wrong));
    let verified = terrastream(&["verify", &url], work);
    assert!(verified.status.success() && text(&verified).contains("OK"), "{}", text(&verified));
    assert!(terrastream(&["extract", &url, "-o", "from-http/sample"], work).status.success());
    assert!(terrastream(&["extract", "d/sample.tspack", "-o", "from-file/sample"], work).status.success());
    assert_eq!(std::fs::read_dir(work.join("from-http/sample/textures/LOD0")).unwrap().count(), 47);
    let missing = terrastream(&["info", &format!("http://127.0.0.1:{port}/nope.tspack")], work);
    assert!(!missing.status.success() && text(&missing).contains("nope.tspack"), "{}", text(&missing));
    let killed = Command::new("kill").args(["-TERM", &server.child.id().to_string()]).status().unwrap();
    assert!(killed.success());
    let status = server.child.wait().unwrap();
    assert!(status.success(), "graceful exit on SIGTERM: {status}");
}

/// `tile`: a dry run prints the plan and writes nothing; a DEM (the committed tiled GeoTIFF
/// crop) plus an image becomes an archive `info` and `verify` accept, with BC7 texture
/// tiles and the height-range layer; an image alone makes a texture-only archive; bad input
/// names the file and leaves nothing under the output name.
#[test]
fn tile_v_names_each_phase_its_time_and_the_cores_it_kept_busy() {
    let dir = tempfile::tempdir().unwrap();
    let dem =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/srtm-tamalpais-150x100-tiled-float32-public-domain.tif");
    let out = terrastream(&["-v", "tile", "--elevation", dem.to_str().unwrap(), "-o", "t.tspack"], dir.path());
    assert!(out.status.success(), "{}", text(&out));
    let log = String::from_utf8_lossy(&out.stderr).to_string();
    for phase in ["planned", "tiles cut and encoded", "tiles handed to the writer", "archive written"] {
        let line = log.lines().find(|l| l.contains(phase)).unwrap_or_else(|| panic!("no {phase:?} line in:\n{log}"));
        assert!(line.contains("took=") && line.contains("elapsed="), "{line}");
        if cfg!(target_os = "linux") {
            // The process's CPU time over the phase's wall time: a number of cores.
            let cores = line.split("cores=").nth(1).and_then(|r| r.split_whitespace().next()).unwrap_or("");
            let cores: f64 = cores.parse().unwrap_or_else(|_| panic!("no cores in {line}"));
            assert!((0.0..=64.0).contains(&cores), "{line}");
        }
    }
}

#[test]
fn tile_plans_writes_and_refuses_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path();
    let dem =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/srtm-tamalpais-150x100-tiled-float32-public-domain.tif");
    let dem = dem.to_str().unwrap();
    // A 120 x 100 image: the DEM's 150 x 100 geographic grid is 120 x 100 in metres.
    let image = work.join("ortho.png");
    let pixels: Vec<u8> = (0..120u32 * 100).flat_map(|i| [(i % 120) as u8 * 2, (i / 120) as u8 * 2, 90]).collect();
    let mut encoder = png::Encoder::new(std::fs::File::create(&image).unwrap(), 120, 100);
    encoder.set_color(png::ColorType::Rgb);
    encoder.write_header().unwrap().write_image_data(&pixels).unwrap();

    let out =
        terrastream(&["tile", "--elevation", dem, "--texture", "ortho.png", "--tile-size", "32", "--dry-run"], work);
    assert!(out.status.success(), "{}", text(&out));
    let plan = text(&out);
    assert!(plan.contains("nothing written") && plan.contains("elevation-range"), "{plan}");
    assert!(plan.contains("heights 148 .. 464,"), "{plan}");
    assert_eq!(std::fs::read_dir(work).unwrap().count(), 1, "a dry run writes nothing");

    let args = ["tile", "--elevation", dem, "--texture", "ortho.png", "--tile-size", "32", "--texture-tile-size", "32"];
    let out = terrastream(&[&args[..], &["--texture-format", "bc7", "-o", "t.tspack"]].concat(), work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["info", "t.tspack", "--json"], work);
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let layers = &doc["metadata"]["layers"];
    assert_eq!(layers[0]["kind"], "elevation");
    // u16 heights gradient-coded (format major 2), as `info` says in words too.
    assert_eq!(
        (layers[0]["format"].as_str(), layers[0]["compression"].as_str()),
        (Some("raw_u16"), Some("zstd_gradient"))
    );
    let words = text(&terrastream(&["info", "t.tspack"], work));
    assert!(words.contains("format 2.0") && words.contains("raw_u16+zstd_gradient"), "{words}");
    assert_eq!((layers[1]["kind"].as_str(), layers[1]["format"].as_str()), (Some("texture"), Some("bc7")));
    assert_eq!((layers[2]["kind"].as_str(), layers[2]["format"].as_str()), (Some("height_range"), Some("min_max_f32")));
    // A geographic DEM goes onto a transverse Mercator centred on it (unless kept).
    let crs = doc["metadata"]["georeference"]["crs"].as_str().unwrap();
    assert!(crs.starts_with("+proj=tmerc +lat_0=37.95") && crs.contains("+lon_0=-122.62"), "{crs}");
    let out = terrastream(&["verify", "t.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["tile", "--elevation", dem, "--keep-geographic", "-o", "kept.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["info", "kept.tspack", "--json"], work);
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(doc["metadata"]["georeference"]["crs"], "EPSG:4326");

    let out = terrastream(&["tile", "--texture", "ortho.png", "--pixel-size", "2", "-o", "img.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["info", "img.tspack", "--json"], work);
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(doc["metadata"]["layers"].as_array().unwrap().len(), 1);
    assert_eq!(doc["metadata"]["layers"][0]["tile_world_size"], 512.0, "256 pixels of 2 m");
    // Placed by a world file (0.5 m pixels in UTM 10N), it keeps its own pixel size.
    std::fs::write(work.join("ortho.pgw"), "0.5\n0\n0\n-0.5\n500000.25\n4200000.75\n").unwrap();
    std::fs::write(work.join("ortho.prj"), r#"PROJCS["WGS_1984_UTM_Zone_10N",GEOGCS["GCS_WGS_1984"]]"#).unwrap();
    let out = terrastream(&["tile", "--texture", "ortho.png", "-o", "placed.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["info", "placed.tspack", "--json"], work);
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(doc["metadata"]["layers"][0]["tile_world_size"], 128.0, "256 pixels of 0.5 m");
    assert_eq!(doc["metadata"]["georeference"]["crs"], "EPSG:32610");
    assert_eq!(doc["metadata"]["georeference"]["origin"], serde_json::json!([500_000.0, 4_200_001.0]));
    std::fs::remove_file(work.join("ortho.pgw")).unwrap();
    // PMTiles round trip: exported, then packed back from the .pmtiles file.
    let out =
        terrastream(&["export", "img.tspack", "--layer", "texture", "--to", "pmtiles", "-o", "img.pmtiles"], work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["pack", "img.pmtiles", "-o", "back.tspack"], work);
    assert!(out.status.success() && text(&out).contains("from PMTiles"), "{}", text(&out));
    let out = terrastream(&["verify", "back.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));

    // A VRT alone is a mosaic of its sources, with their scale: here 1 000 m up.
    let file = terrastream_tiler::open_elevation(Path::new(dem), None).unwrap();
    let (origin, (px, py)) = (file.georeference().unwrap().origin.unwrap(), file.crs_pixel_size().unwrap());
    let vrt = format!(
        r#"<VRTDataset rasterXSize="150" rasterYSize="100"><SRS>EPSG:4326</SRS>
  <GeoTransform>{}, {px}, 0, {}, 0, -{py}</GeoTransform>
  <VRTRasterBand dataType="Float32" band="1"><ComplexSource>
    <SourceFilename relativeToVRT="0">{dem}</SourceFilename><SourceBand>1</SourceBand>
    <SrcRect xOff="0" yOff="0" xSize="150" ySize="100"/><DstRect xOff="0" yOff="0" xSize="150" ySize="100"/>
    <ScaleOffset>1000</ScaleOffset><ScaleRatio>1</ScaleRatio>
  </ComplexSource></VRTRasterBand></VRTDataset>"#,
        origin[0], origin[1]
    );
    std::fs::write(work.join("up.vrt"), vrt).unwrap();
    let out = terrastream(&["tile", "--elevation", "up.vrt", "-o", "up.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["info", "up.tspack", "--json"], work);
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let terrain = &doc["metadata"]["terrain"];
    assert_eq!((terrain["min_elevation"].as_f64(), terrain["max_elevation"].as_f64()), (Some(1148.0), Some(1464.0)));

    std::fs::write(work.join("bad.tif"), b"II*\0garbage").unwrap();
    let out = terrastream(&["tile", "--elevation", "bad.tif", "-o", "bad.tspack"], work);
    assert!(!out.status.success());
    assert!(text(&out).contains("bad.tif"), "{}", text(&out));
    assert!(!work.join("bad.tspack").exists());
    let out = terrastream(&["tile", "--elevation", "ortho.png", "-o", "bad.tspack"], work);
    assert!(!out.status.success() && text(&out).contains("ortho.png"), "{}", text(&out));
    assert!(!work.join("bad.tspack").exists());
    // --skip-bad-inputs: the run goes on without them, and lists them at the end, for
    // heights and imagery alike.
    let out = terrastream(&["tile", "--elevation", dem, "bad.tif", "--skip-bad-inputs", "-o", "some.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("skipped 1 inputs") && text(&out).contains("bad.tif"), "{}", text(&out));
    let out = terrastream(&["tile", "--elevation", dem, "bad.tif", "--skip-bad-inputs", "--dry-run"], work);
    assert!(out.status.success() && text(&out).contains("skipped 1 inputs"), "a plan lists them too: {}", text(&out));
    std::fs::write(work.join("ortho.pgw"), "0.5\n0\n0\n-0.5\n500000.25\n4200000.75\n").unwrap();
    std::fs::write(work.join("bad.png"), b"\x89PNG\r\n\x1a\ngarbage").unwrap();
    let args = ["tile", "--texture", "ortho.png", "bad.png", "--skip-bad-inputs", "-o", "some-img.tspack"];
    let out = terrastream(&args, work);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("skipped 1 inputs") && text(&out).contains("bad.png"), "{}", text(&out));
    let out = terrastream(&["verify", "some-img.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    // An image cut short beside it: found only as its rows are decoded. The run stops
    // naming it, nothing written; with --skip-bad-inputs the rows it holds are used, the
    // rest left empty, and it is listed.
    let bytes = std::fs::read(&image).unwrap();
    std::fs::write(work.join("cut.png"), &bytes[..bytes.len() / 2]).unwrap();
    std::fs::write(work.join("cut.pgw"), "0.5\n0\n0\n-0.5\n500060.25\n4200000.75\n").unwrap();
    std::fs::copy(work.join("ortho.prj"), work.join("cut.prj")).unwrap();
    let out = terrastream(&["tile", "--texture", "ortho.png", "cut.png", "-o", "cut.tspack"], work);
    assert!(!out.status.success() && text(&out).contains("cut.png"), "{}", text(&out));
    assert!(!work.join("cut.tspack").exists());
    let out =
        terrastream(&["tile", "--texture", "ortho.png", "cut.png", "--skip-bad-inputs", "-o", "cut.tspack"], work);
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("cut.png") && text(&out).contains("strips of it left empty"), "{}", text(&out));
}

/// A mosaic of more files than a low limit on open files allows: the binary raises the
/// soft limit to the hard one (as `prlimit` sets them here) and tiles them all.
#[test]
fn a_mosaic_of_many_files_runs_under_a_low_soft_limit_on_open_files() {
    use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
    use tiff::tags::Tag;
    if Command::new("prlimit").arg("--version").output().is_err() {
        eprintln!("skipped: prlimit not found (util-linux)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("tiles")).unwrap();
    // 200 files of 8 x 8 in one row (UTM 33N, 10 m): every band of rows reads them all.
    for k in 0..200u32 {
        let path = dir.path().join(format!("tiles/{k:03}.tif"));
        let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
        let mut image = encoder.new_image::<Gray32Float>(8, 8).unwrap();
        let east = 500_000.0 + f64::from(k) * 80.0;
        image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, 5_100_000.0, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
        image.write_data(&[100.0 + k as f32; 64]).unwrap();
    }
    let bin = env!("CARGO_BIN_EXE_terrastream");
    let out = Command::new("prlimit")
        .args(["--nofile=48:4096", bin, "tile", "--elevation", "tiles", "--crs", "EPSG:32632", "-o", "m.tspack"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["verify", "m.tspack"], dir.path());
    assert!(out.status.success(), "{}", text(&out));
}

/// Imagery alone, asked for in another CRS: one image or several are reprojected into it
/// (the CRS and resolution options are the imagery's when there are no heights).
#[test]
fn imagery_alone_is_tiled_in_the_crs_asked_for() {
    use tiff::encoder::{TiffEncoder, colortype::RGB8};
    use tiff::tags::Tag;
    let dir = tempfile::tempdir().unwrap();
    for (name, east) in [("a.tif", 500_000.0), ("b.tif", 500_640.0)] {
        let mut encoder = TiffEncoder::new(std::fs::File::create(dir.path().join(name)).unwrap()).unwrap();
        let mut image = encoder.new_image::<RGB8>(64, 64).unwrap();
        image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, 5_100_000.0, 0.0][..]).unwrap();
        image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32633][..]).unwrap();
        image.write_data(&[90u8; 64 * 64 * 3]).unwrap();
    }
    for (inputs, resolution) in [(&["a.tif", "b.tif"][..], "10"), (&["a.tif"][..], "20")] {
        let mut args = vec!["tile", "--texture"];
        args.extend(inputs);
        args.extend(["--crs", "EPSG:32632", "--resolution", resolution, "-o", "t.tspack"]);
        let out = terrastream(&args, dir.path());
        assert!(out.status.success(), "{args:?}: {}", text(&out));
        let reader = terrastream_format::Reader::open_mmap(dir.path().join("t.tspack")).unwrap();
        let metadata = reader.metadata();
        let crs = metadata.georeference.as_ref().and_then(|g| g.crs.clone());
        assert_eq!(crs.as_deref(), Some("EPSG:32632"), "{args:?}");
        // Texels of the resolution asked for.
        let layer = &metadata.layers[0];
        let texel = layer.tile_world_size / f64::from(layer.tile_resolution);
        let asked: f64 = resolution.parse().unwrap();
        assert!((texel - asked).abs() < 0.01 * asked, "{args:?}: {texel} m texels");
    }
}

/// A missing archive: the message names the file once and the OS error once.
#[test]
fn a_missing_archive_is_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let out = terrastream(&["info", "missing.tspack"], dir.path());
    assert!(!out.status.success());
    let said = text(&out);
    assert_eq!(said.matches("missing.tspack").count(), 1, "{said}");
    assert_eq!(said.matches("No such file or directory").count(), 1, "{said}");
}

/// `merge --manifest` over a sharded run, then `info` and `verify` of the manifest; a
/// shard replaced by another is named; `tile --manifest-out` names one archive.
#[test]
fn a_sharded_run_is_published_by_a_manifest_that_info_and_verify_read() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let dem = dem.to_str().unwrap();
    for i in 0..3 {
        let shard = format!("{i}/3");
        let out = terrastream(
            &["tile", "--elevation", dem, "--tile-size", "32", "--shard", &shard, "-o", &format!("s{i}.tspack")],
            cwd,
        );
        assert!(out.status.success(), "{}", text(&out));
    }
    let out = terrastream(
        &["merge", "s0.tspack", "s1.tspack", "s2.tspack", "-o", "coarse.tspack", "--manifest", "t.json"],
        cwd,
    );
    assert!(out.status.success(), "{}", text(&out));
    assert!(text(&out).contains("t.json: 4 archives"), "{}", text(&out));
    // Again, into the shards' folder given as the input: its own coarse archive is not one.
    let out = terrastream(&["merge", ".", "-o", "coarse.tspack", "--manifest", "t.json"], cwd);
    assert!(out.status.success() && text(&out).contains("t.json: 4 archives"), "{}", text(&out));
    let out = terrastream(&["info", "t.json"], cwd);
    let info = text(&out);
    assert!(out.status.success() && info.contains("4 archives") && info.contains("s2.tspack"), "{info}");
    let out = terrastream(&["verify", "t.json"], cwd);
    assert!(out.status.success() && text(&out).contains("OK — 4 archives"), "{}", text(&out));
    // Shard 1 replaced by shard 0: its content tag and its tiles' places are named.
    std::fs::copy(cwd.join("s0.tspack"), cwd.join("s1.tspack")).unwrap();
    let out = terrastream(&["verify", "t.json"], cwd);
    let why = text(&out);
    assert_eq!(out.status.code(), Some(2), "{why}");
    assert!(why.contains("archive \"s1.tspack\": content tag") && why.contains("not routed here"), "{why}");
    // One archive, one manifest.
    let out = terrastream(&["tile", "--elevation", dem, "-o", "whole.tspack", "--manifest-out", "whole.json"], cwd);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["verify", "whole.json"], cwd);
    assert!(out.status.success() && text(&out).contains("OK — 1 archives"), "{}", text(&out));
}

#[test]
fn an_update_in_place_is_verified_and_a_merge_compacts_it() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let dem = dem.to_str().unwrap();
    // Published by a manifest, which names the archive by its content tag.
    let tile = ["tile", "--elevation", dem, "--crs", "EPSG:32610", "--tile-size", "32", "-o", "t.tspack"];
    let out = terrastream(&[&tile[..], &["--manifest-out", "t.json"]].concat(), cwd);
    assert!(out.status.success(), "{}", text(&out));
    std::fs::copy(cwd.join("t.json"), cwd.join("stale.json")).unwrap();
    // A re-survey of part of it: heights 10 % higher (GDAL makes it).
    let ok = Command::new("gdal_translate")
        .args([
            "-q", "-srcwin", "100", "100", "80", "60", "-scale", "0", "1000", "0", "1100", "-ot", "Float32", dem,
            "new.tif",
        ])
        .current_dir(cwd)
        .status()
        .unwrap();
    assert!(ok.success());
    let out = terrastream(&["update", "t.tspack", "--elevation", "new.tif"], cwd);
    assert!(!out.status.success() && text(&out).contains("--in-place"), "-o or --in-place: {}", text(&out));
    let before = std::fs::metadata(cwd.join("t.tspack")).unwrap().len();
    let update = ["update", "t.tspack", "--elevation", "new.tif", "--in-place", "--manifest-out", "t.json"];
    let out = terrastream(&update, cwd);
    assert!(out.status.success() && text(&out).contains("base tiles replaced"), "{}", text(&out));
    assert!(std::fs::metadata(cwd.join("t.tspack")).unwrap().len() > before, "appended");
    // The manifest from before the update no longer matches the archive; the one written
    // with the update does.
    let out = terrastream(&["verify", "stale.json"], cwd);
    assert!(!out.status.success() && text(&out).contains("content tag"), "{}", text(&out));
    let out = terrastream(&["verify", "t.json"], cwd);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["verify", "t.tspack"], cwd);
    let report = text(&out);
    assert!(out.status.success() && report.contains("OK") && report.contains("bytes of replaced tiles"), "{report}");
    let out = terrastream(&["merge", "t.tspack", "-o", "compact.tspack"], cwd);
    assert!(out.status.success(), "{}", text(&out));
    let out = terrastream(&["verify", "compact.tspack"], cwd);
    let report = text(&out);
    assert!(out.status.success() && report.contains("OK") && !report.contains("replaced"), "{report}");
    let tiles = |name: &str| {
        let out = terrastream(&["info", name, "--json"], cwd);
        let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        info["stats"]["addressed_tiles"].as_u64()
    };
    assert_eq!(tiles("t.tspack"), tiles("compact.tspack"));
    assert!(tiles("t.tspack").is_some_and(|n| n > 10));
}

/// A planned sharded run, as the cluster Job runs it: the plan, from the inputs' headers,
/// lists for each shard the inputs its band reads (their union is every input, and each
/// shard's is a part); a shard given only those and the plan makes the tiles a shard given
/// every input makes, and the merge of such shards is the whole run. A listed input
/// missing is named.
#[test]
fn a_shard_of_a_planned_run_needs_only_the_inputs_its_plan_lists() {
    use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
    use tiff::tags::Tag;
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    std::fs::create_dir(cwd.join("in")).unwrap();
    // 6 rows x 4 columns of 40 x 40 samples at 10 m in UTM 32N, reprojected onto 33N.
    let mut names = vec![];
    for row in 0..6u32 {
        for col in 0..4u32 {
            let name = format!("r{row}c{col}.tif");
            let mut encoder = TiffEncoder::new(std::fs::File::create(cwd.join("in").join(&name)).unwrap()).unwrap();
            let mut image = encoder.new_image::<Gray32Float>(40, 40).unwrap();
            let (east, north) = (780_000.0 + f64::from(col) * 400.0, 5_100_000.0 - f64::from(row) * 400.0);
            image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
            image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, north, 0.0][..]).unwrap();
            image
                .encoder()
                .write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32632][..])
                .unwrap();
            let data: Vec<f32> = (0..1600u32)
                .map(|i| {
                    let (x, y) = (east + f64::from(i % 40) * 10.0, north - f64::from(i / 40) * 10.0);
                    (300.0 + 80.0 * (x / 310.0).sin() + 50.0 * (y / 170.0).cos()) as f32
                })
                .collect();
            image.write_data(&data).unwrap();
            names.push(format!("in/{name}"));
        }
    }
    let common = ["--crs", "EPSG:32633", "--tile-size", "32", "--height-range", "0,1000"];
    let with = |first: &[&str]| -> Vec<String> { first.iter().chain(&common).map(|s| (*s).to_owned()).collect() };
    let run = |args: &[String], cwd: &Path| {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = terrastream(&args, cwd);
        assert!(out.status.success(), "{args:?}: {}", text(&out));
        text(&out)
    };
    run(&with(&["tile", "--elevation", "in", "--shards", "3", "--shard-plan-out", "plan", "--relative-to", "in"]), cwd);
    let lists: Vec<Vec<String>> = (0..3)
        .map(|i| {
            let list = std::fs::read_to_string(cwd.join(format!("plan/shard-{i}.txt"))).unwrap();
            list.lines().map(|l| format!("in/{l}")).collect()
        })
        .collect();
    let mut union: Vec<String> = lists.iter().flatten().cloned().collect();
    union.sort();
    union.dedup();
    assert_eq!(union, names, "every input is some shard's");
    for (i, list) in lists.iter().enumerate() {
        assert!(!list.is_empty() && list.len() < names.len() * 2 / 3, "shard {i} reads {list:?}");
        // `--list-inputs` says the same.
        let shard = format!("{i}/3");
        let args = with(&["tile", "--elevation", "in", "--shard", &shard, "--list-inputs"]);
        let out = terrastream(&args.iter().map(String::as_str).collect::<Vec<_>>(), cwd);
        let said = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{}", text(&out));
        assert_eq!(said.lines().map(str::to_owned).collect::<Vec<_>>(), *list, "shard {i}");
    }
    // Each shard in a folder of its own holding only its inputs (as a pod fetches them).
    let plan = cwd.join("plan/plan.json");
    let plan = plan.to_str().unwrap();
    let mut planned = vec![];
    for (i, list) in lists.iter().enumerate() {
        let pod = cwd.join(format!("pod{i}"));
        std::fs::create_dir_all(pod.join("in")).unwrap();
        for name in list {
            std::fs::copy(cwd.join(name), pod.join(name)).unwrap();
        }
        let (shard, out) = (format!("{i}/3"), cwd.join(format!("p{i}.tspack")));
        let out = out.to_str().unwrap();
        run(&with(&["tile", "--elevation", "in", "--shard", &shard, "--shard-plan", plan, "-o", out]), &pod);
        let whole = format!("w{i}.tspack");
        run(&with(&["tile", "--elevation", "in", "--shard", &shard, "-o", &whole]), cwd);
        let (a, b) = (stored_tiles(&cwd.join(format!("p{i}.tspack"))), stored_tiles(&cwd.join(&whole)));
        assert!(!a.is_empty());
        assert!(a == b, "shard {i}: {} tiles from its inputs, {} from all; they differ", a.len(), b.len());
        planned.push(format!("p{i}.tspack"));
    }
    let merge: Vec<&str> =
        ["merge"].into_iter().chain(planned.iter().map(String::as_str)).chain(["-o", "m.tspack"]).collect();
    let out = terrastream(&merge, cwd);
    assert!(out.status.success(), "{}", text(&out));
    run(&with(&["tile", "--elevation", "in", "-o", "whole.tspack"]), cwd);
    assert!(stored_tiles(&cwd.join("m.tspack")) == stored_tiles(&cwd.join("whole.tspack")), "merged shards");
    // A VRT cannot be split between shards: said, naming it.
    std::fs::write(cwd.join("all.vrt"), "<VRTDataset rasterXSize=\"1\" rasterYSize=\"1\"></VRTDataset>").unwrap();
    let out = terrastream(&["tile", "--elevation", "all.vrt", "--shards", "2", "--shard-plan-out", "vplan"], cwd);
    assert!(!out.status.success() && text(&out).contains("all.vrt: a VRT cannot be split"), "{}", text(&out));
    assert!(!cwd.join("vplan").exists());
    // A listed input missing: named, nothing written.
    let pod = cwd.join("pod0");
    std::fs::remove_file(pod.join(&lists[0][0])).unwrap();
    let args = with(&["tile", "--elevation", "in", "--shard", "0/3", "--shard-plan", plan, "-o", "again.tspack"]);
    let out = terrastream(&args.iter().map(String::as_str).collect::<Vec<_>>(), &pod);
    let missing = lists[0][0].strip_prefix("in/").unwrap();
    assert!(!out.status.success() && text(&out).contains(&format!("reads {missing}")), "{}", text(&out));
    assert!(!pod.join("again.tspack").exists());
}

/// A UTM 32N GeoTIFF of 40 x 40 samples at 10 m whose heights run from `base` to
/// `base + 78`, with GDAL's statistics tag saying `statistics` (XML items), if given.
fn stats_geotiff(path: &Path, east: f64, base: f32, statistics: Option<&str>) {
    use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
    use tiff::tags::Tag;
    let mut encoder = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    let mut image = encoder.new_image::<Gray32Float>(40, 40).unwrap();
    image.encoder().write_tag(Tag::Unknown(33550), &[10.0, 10.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(33922), &[0.0, 0.0, 0.0, east, 5_100_000.0, 0.0][..]).unwrap();
    image.encoder().write_tag(Tag::Unknown(34735), &[1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, 32632][..]).unwrap();
    if let Some(items) = statistics {
        image.encoder().write_tag(Tag::Unknown(42112), &*format!("<GDALMetadata>{items}</GDALMetadata>")).unwrap();
    }
    let data: Vec<f32> = (0..1600u32).map(|i| base + (i % 40 + i / 40) as f32).collect();
    image.write_data(&data).unwrap();
}

/// The plan step's height range comes from the inputs' GDAL statistics when every one
/// records exact ones (no height read: the range is what they say), and from a scan when
/// one is approximate; a shard given a range the data leaves stops, naming the file.
#[test]
fn a_plans_height_range_comes_from_the_inputs_statistics_and_shards_check_it() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let stats = |min: f32, max: f32, approximate: bool| {
        let mut items = format!(
            r#"<Item name="STATISTICS_MAXIMUM" sample="0">{max}</Item><Item name="STATISTICS_MINIMUM" sample="0">{min}</Item>"#
        );
        if approximate {
            items.push_str(r#"<Item name="STATISTICS_APPROXIMATE" sample="0">YES</Item>"#);
        }
        items
    };
    let range_of = |folder: &str| {
        let out = terrastream(&["tile", "--elevation", folder, "--dry-run", "--height-range-out", "r.txt"], cwd);
        assert!(out.status.success(), "{}", text(&out));
        std::fs::read_to_string(cwd.join("r.txt")).unwrap().trim().to_owned()
    };
    // Exact statistics, wider than the data (100..178, 300..378): the range is theirs.
    std::fs::create_dir(cwd.join("exact")).unwrap();
    stats_geotiff(&cwd.join("exact/a.tif"), 500_000.0, 100.0, Some(&stats(90.0, 180.0, false)));
    stats_geotiff(&cwd.join("exact/b.tif"), 500_400.0, 300.0, Some(&stats(295.5, 400.0, false)));
    assert_eq!(range_of("exact"), "90,400");
    // One approximate: every height is scanned.
    std::fs::create_dir(cwd.join("approx")).unwrap();
    stats_geotiff(&cwd.join("approx/a.tif"), 500_000.0, 100.0, Some(&stats(90.0, 180.0, false)));
    stats_geotiff(&cwd.join("approx/b.tif"), 500_400.0, 300.0, Some(&stats(295.5, 400.0, true)));
    assert_eq!(range_of("approx"), "100,378");
    // Statistics that lie (b's heights reach 378): the shard reading b stops, naming it.
    std::fs::create_dir(cwd.join("lying")).unwrap();
    stats_geotiff(&cwd.join("lying/a.tif"), 500_000.0, 100.0, Some(&stats(100.0, 178.0, false)));
    stats_geotiff(&cwd.join("lying/b.tif"), 500_400.0, 300.0, Some(&stats(300.0, 310.0, false)));
    assert_eq!(range_of("lying"), "100,310");
    let out = terrastream(
        &["tile", "--elevation", "lying", "--shard", "0/1", "--height-range", "@r.txt", "-o", "s.tspack"],
        cwd,
    );
    assert!(!out.status.success() && text(&out).contains("b.tif"), "{}", text(&out));
    assert!(!cwd.join("s.tspack").exists());
}

/// The cluster's plan step on the inputs' headers alone: COGs written by GDAL with their
/// statistics (`gdal_translate -of COG -stats`), of which the plan pod fetches the first
/// 16 KiB and leaves the rest a hole. The height range and the shard plan are the ones the
/// whole files give, though the holes hold no heights.
#[test]
fn a_shard_plan_from_the_inputs_headers_alone_is_the_plan_of_the_whole_files() {
    if Command::new("gdal_translate").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "gdal_translate is not installed (gdal-bin)");
        eprintln!("skipped: gdal_translate not found (gdal-bin)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    for d in ["raw", "full", "heads"] {
        std::fs::create_dir(cwd.join(d)).unwrap();
    }
    for row in 0..3u32 {
        for col in 0..2u32 {
            let name = format!("r{row}c{col}.tif");
            let raw = cwd.join("raw").join(&name);
            stats_geotiff(&raw, 500_000.0 + f64::from(col) * 400.0, 100.0 * row as f32, None);
            // Move it down a row of files: rewrite the tie point.
            let north = 5_100_000.0 - f64::from(row) * 400.0;
            let out = Command::new("gdal_translate")
                .args([
                    "-q",
                    "-of",
                    "COG",
                    "-stats",
                    "-co",
                    "COMPRESS=NONE",
                    "-co",
                    "BLOCKSIZE=32",
                    "-outsize",
                    "400%",
                    "400%",
                ])
                .args(["-a_ullr", &(500_000.0 + f64::from(col) * 400.0).to_string(), &north.to_string()])
                .args([&(500_400.0 + f64::from(col) * 400.0).to_string(), &(north - 400.0).to_string()])
                .arg(&raw)
                .arg(cwd.join("full").join(&name))
                .output()
                .unwrap();
            assert!(out.status.success(), "{}", text(&out));
            let bytes = std::fs::read(cwd.join("full").join(&name)).unwrap();
            assert!(bytes.len() > 16_384, "a file larger than its head");
            let head = cwd.join("heads").join(&name);
            std::fs::write(&head, &bytes[..16_384]).unwrap();
            std::fs::File::options().write(true).open(&head).unwrap().set_len(bytes.len() as u64).unwrap();
        }
    }
    let plan = |folder: &str| {
        let common = ["--elevation", folder, "--crs", "EPSG:32633", "--tile-size", "32"];
        let range = format!("{folder}-range.txt");
        let args: Vec<&str> = ["tile"]
            .into_iter()
            .chain(common)
            .chain(["--dry-run", "--height-range-out", &range, "--require-statistics"])
            .collect();
        let out = terrastream(&args, cwd);
        assert!(out.status.success(), "{}", text(&out));
        let to = format!("{folder}-plan");
        let args: Vec<&str> = ["tile"]
            .into_iter()
            .chain(common)
            .chain(["--shards", "3", "--shard-plan-out", &to, "--relative-to", folder])
            .collect();
        let out = terrastream(&args, cwd);
        assert!(out.status.success(), "{}", text(&out));
        let read = |p: String| std::fs::read_to_string(cwd.join(p)).unwrap();
        (
            read(range),
            read(format!("{to}/plan.json")),
            (0..3).map(|i| read(format!("{to}/shard-{i}.txt"))).collect::<Vec<_>>(),
        )
    };
    let (whole, heads) = (plan("full"), plan("heads"));
    assert_eq!(whole.0.trim(), "0,278", "the range GDAL's statistics give");
    assert_eq!(whole, heads, "the plan of the headers alone");
    assert!(whole.2.iter().all(|l| l.lines().count() < 6), "each shard a part: {:?}", whole.2);
    // The holes hold no heights (tiles made from them are not the files' tiles): what the
    // plan gave, it took from the headers.
    for folder in ["full", "heads"] {
        let out = format!("{folder}.tspack");
        let args = ["tile", "--elevation", folder, "--crs", "EPSG:32633", "--height-range", "0,278", "-o", &out];
        let said = terrastream(&args, cwd);
        assert!(said.status.success(), "{}", text(&said));
    }
    assert!(stored_tiles(&cwd.join("full.tspack")) != stored_tiles(&cwd.join("heads.tspack")));
}

/// The publish step from the shards' tops: `info --shard-top-out` names the prefix of a
/// shard that holds its tiles at the split LOD (less than the shard); `merge --manifest`
/// over copies holding only that prefix (the rest a hole, as the cluster's merge pod
/// fetches them) writes the coarse archive and manifest the whole shards give.
#[test]
fn a_manifest_is_published_from_the_shards_tops_alone() {
    let dir = tempfile::tempdir().unwrap();
    let cwd = dir.path();
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let dem = dem.to_str().unwrap();
    for d in ["whole", "tops"] {
        std::fs::create_dir(cwd.join(d)).unwrap();
    }
    for i in 0..2 {
        let (shard, out) = (format!("{i}/2"), format!("whole/shard-{i}.tspack"));
        let args = ["tile", "--elevation", dem, "--tile-size", "32", "--shard", &shard, "--split-lod", "2", "-o", &out];
        let said = terrastream(&args, cwd);
        assert!(said.status.success(), "{}", text(&said));
        let top = format!("whole/shard-{i}.top");
        let said = terrastream(&["info", &out, "--shard-top-out", &top], cwd);
        assert!(said.status.success(), "{}", text(&said));
        let top: usize = std::fs::read_to_string(cwd.join(&top)).unwrap().trim().parse().unwrap();
        let bytes = std::fs::read(cwd.join(&out)).unwrap();
        assert!(top > 128 && top < bytes.len() / 2, "a top of {top} bytes of {}", bytes.len());
        let copy = cwd.join(format!("tops/shard-{i}.tspack"));
        std::fs::write(&copy, &bytes[..top]).unwrap();
        std::fs::File::options().write(true).open(&copy).unwrap().set_len(bytes.len() as u64).unwrap();
    }
    for d in ["whole", "tops"] {
        let (coarse, manifest) = (format!("{d}/coarse.tspack"), format!("{d}/terrain.json"));
        let said = terrastream(&["merge", d, "-o", &coarse, "--manifest", &manifest], cwd);
        assert!(said.status.success(), "{d}: {}", text(&said));
    }
    assert_eq!(stored_tiles(&cwd.join("whole/coarse.tspack")), stored_tiles(&cwd.join("tops/coarse.tspack")));
    let read = |p: &str| std::fs::read_to_string(cwd.join(p)).unwrap();
    assert_eq!(read("whole/terrain.json"), read("tops/terrain.json"));
    // Not a shard: said so.
    let said = terrastream(&["info", "whole/coarse.tspack", "--shard-top-out", "x.top"], cwd);
    assert!(!said.status.success() && text(&said).contains("not a shard"), "{}", text(&said));
}

/// Where stderr is not a terminal (a pod's log), progress comes as lines: each phase's size,
/// then how far it is, how fast and how long is left.
#[test]
fn progress_is_logged_as_lines_where_there_is_no_terminal() {
    let dir = tempfile::tempdir().unwrap();
    let dem = terrastream_testkit::golden::repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif");
    let out = terrastream(
        &["--log-progress", "0", "tile", "--elevation", dem.to_str().unwrap(), "--tile-size", "32", "-o", "t.tspack"],
        dir.path(),
    );
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    let lines: Vec<&str> = said.lines().filter(|l| l.contains(" %), ")).collect();
    assert!(lines.iter().filter(|l| l.contains("tile: ")).count() > 2, "{said}");
    // The last phase (writing the archive) logs its end.
    assert!(lines.last().unwrap().contains("(100.0 %)"), "{said}");
    assert!(said.contains("tile: ") && said.contains(" to do"), "{said}");
    // -q: none.
    let out = terrastream(
        &[
            "-q",
            "--log-progress",
            "0",
            "tile",
            "--elevation",
            dem.to_str().unwrap(),
            "--tile-size",
            "32",
            "-o",
            "u.tspack",
        ],
        dir.path(),
    );
    assert!(out.status.success() && !text(&out).contains(" %), "), "{}", text(&out));
}

/// `bench render` flies every row on the built-in crop (tiny frames: its numbers are not
/// checked, only that each row is drawn and the descent always shows terrain).
#[test]
fn bench_render_flies_every_row_and_the_descent_shows_terrain() {
    let dir = tempfile::tempdir().unwrap();
    let out = terrastream(&["bench", "render", "--frames", "3", "--size", "96x54"], dir.path());
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    for row in ["streaming ", "resident ", "baseline ", "globe ", "globe baseline ", "atmosphere ", "globe, in turn "] {
        assert!(
            said.lines().any(|l| l.trim_start().starts_with(row) && l.contains("frame ms median")),
            "{row}: {said}"
        );
    }
    assert!(said.contains("the atmosphere's share of the globe's frame (median, frames in turn)"), "{said}");
    assert!(said.contains(", 0 without terrain;"), "{said}");
}
