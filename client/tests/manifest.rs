//! A terrain published as several archives: three shards of a run plus the coarse archive
//! `merge --manifest` makes, named by a manifest. Read through the manifest (from files,
//! from nginx as a static host, from our server), every view renders byte-identical to
//! the merged single archive, and each request goes to the archive that holds its tiles.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DVec3;
use terrastream_client::Surface;
use terrastream_client::render::gpu::Gpu;
use terrastream_client::render::renderer::RenderSettings;
use terrastream_client::render::still::{Still, StillOptions, default_camera, render_still};
use terrastream_client::{Camera, Origin, StreamOptions, Streamer};
use terrastream_format::{Manifest, Metadata};
use terrastream_pack::progress::Silent;
use terrastream_testkit::golden::repo;
use terrastream_tiler::{
    Image, ShardSpec, TextureFormat, TextureInput, TileOptions, merge, merge_to_manifest, read_geotiff, tile_shard,
};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 200;

fn gpu() -> Option<Gpu> {
    match Gpu::headless() {
        Ok(gpu) => Some(gpu),
        Err(e) if std::env::var_os("TERRASTREAM_ALLOW_NO_GPU").is_some() => {
            eprintln!("\n!!!!! SKIPPING: {e} (TERRASTREAM_ALLOW_NO_GPU is set) !!!!!\n");
            None
        }
        Err(e) => panic!("{e}: install mesa-vulkan-drivers, or set TERRASTREAM_ALLOW_NO_GPU=1 to skip"),
    }
}

/// The published folder (shards up to `split_lod`): `tamalpais.json`, `coarse.tspack`, `shard-{0,1,2}.tspack`; and
/// the merged single archive beside it.
struct Published {
    _dir: tempfile::TempDir,
    folder: PathBuf,
    merged: PathBuf,
    manifest: Manifest,
}

fn publish(split_lod: u8) -> Published {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("pub");
    std::fs::create_dir(&folder).unwrap();
    let dem = read_geotiff(&repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif")).unwrap();
    // Imagery with a grid every 40 pixels: a misplaced tile shows.
    let (w, h) = (dem.width, dem.height);
    let rgba = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .flat_map(|(x, y)| {
            let line = x % 40 == 0 || y % 40 == 0;
            if line { [20, 20, 20, 255] } else { [(x * 255 / w) as u8, 160, (y * 255 / h) as u8, 255] }
        })
        .collect();
    let image = Image { width: w, height: h, rgba, georeference: None };
    let texture = || TextureInput { source: &image, tile_size: 32, format: TextureFormat::Png, pixel_size: 1.0 };
    let options = TileOptions { tile_size: 32, border: 1, ..TileOptions::default() };
    let shards: Vec<PathBuf> = (0..3)
        .map(|i| {
            let out = folder.join(format!("shard-{i}.tspack"));
            let spec = ShardSpec { index: i, count: 3, split_lod: Some(split_lod), cuts: None };
            tile_shard(Some(&dem), Some(texture()), "tamalpais", &out, options, Some(spec), &Silent::default())
                .unwrap();
            out
        })
        .collect();
    let merged = dir.path().join("merged.tspack");
    merge(&shards, &merged, &Silent::default()).unwrap();
    let summary = merge_to_manifest(
        &shards,
        &folder.join("coarse.tspack"),
        &folder.join("tamalpais.json"),
        None,
        terrastream_tiler::RunInputs::default(),
        &Silent::default(),
    )
    .unwrap();
    Published { _dir: dir, folder, merged, manifest: summary.manifest }
}

fn camera(eye: [f64; 3], target: [f64; 3]) -> Camera {
    Camera::look_at(DVec3::from_array(eye), DVec3::from_array(target), WIDTH, HEIGHT)
}

fn render(gpu: &Gpu, location: &str, cam: Option<Camera>) -> Still {
    let options = StillOptions {
        width: WIDTH,
        height: HEIGHT,
        settings: RenderSettings { flat: true, ..RenderSettings::default() },
        ..StillOptions::default()
    };
    let camera = |m: &Metadata, s: &Surface| Ok(cam.unwrap_or_else(|| default_camera(m, s, WIDTH, HEIGHT)));
    render_still(gpu, Origin::parse(location).unwrap(), camera, &options).unwrap()
}

/// The views compared: the default (whole terrain) and a grazing one down to LOD 0 across
/// all three bands.
fn views() -> [Option<Camera>; 2] {
    [None, Some(camera([2200.0, 650.0, 9200.0], [5000.0, 350.0, 2500.0]))]
}

/// Requests in an nginx access log written as `$uri $status $http_range`: per file, the
/// statuses and ranges.
fn requests(log: &Path) -> BTreeMap<String, Vec<(u16, String)>> {
    let mut out: BTreeMap<String, Vec<(u16, String)>> = BTreeMap::new();
    for line in std::fs::read_to_string(log).unwrap_or_default().lines() {
        let mut parts = line.split(' ');
        let (uri, status, range) = (parts.next().unwrap(), parts.next().unwrap(), parts.next().unwrap_or("-"));
        out.entry(uri.trim_start_matches('/').to_owned()).or_default().push((status.parse().unwrap(), range.into()));
    }
    out
}

#[test]
fn a_four_archive_manifest_renders_as_the_merged_archive_from_files_nginx_and_our_server() {
    let Some(gpu) = gpu() else { return };
    let p = publish(1);
    let urls: Vec<&str> = p.manifest.archives.iter().map(|a| a.url.as_str()).collect();
    assert_eq!(urls, ["coarse.tspack", "shard-0.tspack", "shard-1.tspack", "shard-2.tspack"]);
    let manifest_path = p.folder.join("tamalpais.json");
    let log_dir = tempfile::tempdir().unwrap();
    let log = log_dir.path().join("access.log");
    let block = format!(
        "log_format ranges '$uri $status $http_range';\n\
         server {{ listen 127.0.0.1:{{port}}; root {{root}}; access_log {} ranges; }}",
        log.display()
    );
    let nginx = terrastream_testkit::nginx::start_nginx(&p.folder, &block);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let state = terrastream_testkit::server::state(&p.folder);
    let (addr, server) =
        runtime.block_on(terrastream_testkit::server::serve_router(terrastream_server::app(state), "127.0.0.1:0"));
    for (i, view) in views().into_iter().enumerate() {
        let expected = render(&gpu, p.merged.to_str().unwrap(), view);
        assert!(expected.stream.uploads > 8, "view {i}: the merged archive draws terrain");
        let mut sources = vec![manifest_path.display().to_string(), format!("http://{addr}/tamalpais.json")];
        if let Some(nginx) = &nginx {
            sources.push(format!("http://127.0.0.1:{}/tamalpais.json", nginx.port));
        }
        for source in sources {
            let got = render(&gpu, &source, view);
            assert_eq!(got.stream.missing, expected.stream.missing, "view {i} from {source}: tiles found missing");
            assert!(got.rgba == expected.rgba, "view {i} from {source}: not the merged archive's image");
        }
    }
    server.abort();
    let Some(_nginx) = nginx else { return };
    let seen = requests(&log);
    // The manifest, then Range requests to each of its four archives, all answered.
    assert!(seen["tamalpais.json"].iter().all(|(status, _)| *status == 200));
    for url in urls {
        let asked = seen.get(url).unwrap_or_else(|| panic!("no request for {url}: {seen:?}"));
        assert!(asked.iter().all(|(status, range)| *status == 206 && range.starts_with("bytes=")), "{url}: {asked:?}");
    }
    assert_eq!(seen.len(), 5, "nothing but the manifest and its archives: {:?}", seen.keys());
}

/// A view of the northern band alone opens only the archives that hold its tiles: the
/// coarse one and the northern shards; a height asked at a point of the third band opens it.
#[test]
fn only_the_archives_a_view_needs_are_opened() {
    // Shards of LOD 0 only: a near view wants LOD-0 tiles of a few rows alone.
    let p = publish(0);
    let manifest_path = p.folder.join("tamalpais.json");
    let origin = Origin::parse(manifest_path.to_str().unwrap()).unwrap();
    let mut streamer = Streamer::open(origin, StreamOptions::default()).unwrap();
    let metadata = streamer.metadata().unwrap().clone();
    assert_eq!(metadata, p.manifest.metadata);
    // Straight down from 400 m over the north-west corner: LOD-0 tiles of the top rows.
    let cam = Camera::look_at(DVec3::new(800.0, 400.0, 600.0), DVec3::new(800.0, 0.0, 601.0), WIDTH, HEIGHT);
    for _ in 0..400 {
        streamer.update(&cam);
        streamer.drain_uploads(terrastream_client::UploadBudget { max_tiles: 64, max_bytes: 64 << 20 });
        if streamer.pending() == 0 && !streamer.wanted().is_empty() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert_eq!(streamer.pending(), 0, "{:?}", streamer.stats());
    assert!(streamer.wanted().iter().any(|w| w.key.lod() == 0), "the view reaches LOD 0");
    // Exactly the archives holding a wanted tile were opened, and not all of them.
    let mut needed = vec![false; p.manifest.archives.len()];
    for w in streamer.wanted() {
        needed[p.manifest.route(w.key).unwrap().part] = true;
    }
    assert_eq!(streamer.opened_parts(), needed);
    assert!(!needed[3], "the southern band's shard is not needed here");
    // A height in the southern band: its shard is opened for it.
    let extent = metadata.layers[0].world_extent();
    let h = streamer.height_at_exact(extent.0 / 2.0, extent.1 - 50.0).unwrap();
    assert!(h.is_some_and(|h| h > -10.0 && h < 800.0), "{h:?}");
    needed[3] = true;
    assert_eq!(streamer.opened_parts(), needed);
}

/// An archive the manifest names is missing: the tiles it holds stay wanted (retried with
/// a backoff), the error names the archive, and the other archives stream on.
#[test]
fn a_missing_archive_is_named_and_the_rest_streams() {
    let p = publish(0);
    std::fs::remove_file(p.folder.join("shard-2.tspack")).unwrap();
    let origin = Origin::parse(p.folder.join("tamalpais.json").to_str().unwrap()).unwrap();
    let mut streamer = Streamer::open(origin, StreamOptions::default()).unwrap();
    let metadata = streamer.metadata().unwrap().clone();
    let cam = default_camera(&metadata, &Surface::Flat, WIDTH, HEIGHT);
    for _ in 0..200 {
        streamer.update(&cam);
        streamer.drain_uploads(terrastream_client::UploadBudget { max_tiles: 64, max_bytes: 64 << 20 });
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let error = streamer.last_error().unwrap_or_default().to_owned();
    assert!(error.contains("shard-2.tspack"), "{error}");
    assert!(!streamer.opened_parts()[3], "the missing archive is not open");
    assert!(streamer.pending() > 0, "the missing archive's tiles are still wanted");
    assert!(streamer.stats().uploads > 8, "the others stream: {:?}", streamer.stats());
}

/// A manifest republished on the server (a region's archive under a new name, the old one
/// removed): a streaming client asks again every `manifest_recheck` (a conditional
/// request), finds it changed, and re-reads everything from the new one.
#[test]
fn a_republished_manifest_is_picked_up_while_streaming() {
    let p = publish(0);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let state = terrastream_testkit::server::state(&p.folder);
    let catalog = state.catalog.clone();
    let (addr, server) =
        runtime.block_on(terrastream_testkit::server::serve_router(terrastream_server::app(state), "127.0.0.1:0"));
    let options = StreamOptions { manifest_recheck: std::time::Duration::from_millis(50), ..StreamOptions::default() };
    let origin = Origin::parse(&format!("http://{addr}/tamalpais.json")).unwrap();
    let mut streamer = Streamer::open(origin, options).unwrap();
    let cam = default_camera(streamer.metadata().unwrap(), &Surface::Flat, WIDTH, HEIGHT);
    let stream_until = |s: &mut Streamer, done: &dyn Fn(&Streamer) -> bool| {
        for _ in 0..1000 {
            s.update(&cam);
            s.drain_uploads(terrastream_client::UploadBudget { max_tiles: 64, max_bytes: 64 << 20 });
            if done(s) {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        panic!("not done: {:?}, last error {:?}", s.stats(), s.last_error());
    };
    stream_until(&mut streamer, &|s| s.pending() == 0 && !s.wanted().is_empty());
    assert_eq!(streamer.stats().reloads, 0, "asked again, unchanged: nothing re-read");

    // The view streams from shard 1, among others.
    assert!(streamer.opened_parts()[2], "{:?}", streamer.opened_parts());
    // Republished: shard 1 under a new name, the manifest last, the old file removed.
    let mut manifest = p.manifest.clone();
    assert_eq!(manifest.archives[2].url, "shard-1.tspack");
    manifest.archives[2].url = "shard-1b.tspack".into();
    std::fs::copy(p.folder.join("shard-1.tspack"), p.folder.join("shard-1b.tspack")).unwrap();
    terrastream_tiler::write_manifest(&manifest, &p.folder.join("tamalpais.json")).unwrap();
    std::fs::remove_file(p.folder.join("shard-1.tspack")).unwrap();
    catalog.reload();
    // Re-read from the new manifest: the view completes again, shard 1 from its new name
    // (the old one is gone: reading it would fail).
    stream_until(&mut streamer, &|s| s.stats().reloads == 1 && s.pending() == 0 && !s.wanted().is_empty());
    assert!(streamer.opened_parts()[2], "the new shard-1b opened");
    assert_eq!(streamer.stats().failures, 0, "{:?}", streamer.last_error());
    server.abort();
}
