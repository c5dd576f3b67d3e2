//! Rendering, on whatever adapter wgpu finds (the test command installs Mesa's lavapipe):
//! golden images of a real DEM crop (SRTM 1", Mt Tamalpais; public domain) from several
//! views, identical images from mmap and from HTTP, and a crack count on a flat-white render.
//!
//! Golden images live in `tests/golden/`. `TERRASTREAM_BLESS=1` (re)writes them; a missing
//! one fails. Without an adapter the tests fail unless `TERRASTREAM_ALLOW_NO_GPU=1`, which
//! skips them loudly (for machines without Mesa; never set on CI).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

#[path = "../../tests/support/golden.rs"]
mod golden;

#[path = "../../server/tests/common/mod.rs"]
mod common;
mod support;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use glam::DVec3;
use terrastream_client::render::gpu::Gpu;
use terrastream_client::render::renderer::{RenderSettings, Shading};
use terrastream_client::render::still::{Still, StillOptions, default_camera, render_still};
use terrastream_client::render::wgpu;
use terrastream_client::{Camera, Origin};
use terrastream_packer::progress::Silent;
use terrastream_packer::tiler::{TileOptions, read_geotiff, tile_elevation};
use terrastream_packer::{Metadata, Reader, Writer, WriterOptions};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 200;

use golden::repo;

/// One device for all tests of this binary (lavapipe is slow to start).
fn gpu() -> Option<&'static Gpu> {
    static GPU: OnceLock<Option<Gpu>> = OnceLock::new();
    GPU.get_or_init(|| match Gpu::headless() {
        Ok(gpu) => {
            eprintln!("rendering on {}", gpu.describe());
            Some(gpu)
        }
        Err(e) if std::env::var_os("TERRASTREAM_ALLOW_NO_GPU").is_some() => {
            eprintln!("\n!!!!! SKIPPING RENDER TESTS: {e} (TERRASTREAM_ALLOW_NO_GPU is set) !!!!!\n");
            None
        }
        Err(e) => panic!(
            "{e}: install mesa-vulkan-drivers (the test command does), or set TERRASTREAM_ALLOW_NO_GPU=1 to skip"
        ),
    })
    .as_ref()
}

/// The committed DEM crop, tiled like `terrastream tile --tile-size 64`.
fn dem_archive() -> &'static Path {
    static ARCHIVE: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &ARCHIVE
        .get_or_init(|| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("tamalpais.tspack");
            let raster = read_geotiff(&repo().join("tests/data/srtm-tamalpais-320-public-domain.tif")).unwrap();
            let options = TileOptions { tile_size: 64, border: 1, ..TileOptions::default() };
            tile_elevation(raster, "tamalpais", &path, options, &Silent::default()).unwrap();
            (dir, path)
        })
        .1
}

/// The same archive without its two finest LODs east of x = 2 tiles: a sparse pyramid.
fn sparse_archive(dir: &Path) -> PathBuf {
    let reader = Reader::open_mmap(dem_archive()).unwrap();
    let metadata: Metadata = reader.metadata().clone();
    let path = dir.join("sparse.tspack");
    let mut writer = Writer::create(&path, metadata.clone(), WriterOptions::default()).unwrap();
    let layer = &metadata.layers[0];
    let mut keys: Vec<_> = (0..layer.num_lods)
        .flat_map(|lod| layer.tiles_at(0, lod))
        .filter(|k| !(k.lod() < 2 && (k.x() << k.lod()) >= 2))
        .collect();
    keys.sort_by_key(|k| Writer::order_key(&metadata, *k).unwrap());
    for key in keys {
        if let Some(stored) = reader.tile(key).unwrap() {
            writer.add_stored(key, stored.to_vec()).unwrap();
        }
    }
    writer.finish().unwrap();
    path
}

fn camera(eye: [f64; 3], target: [f64; 3]) -> Camera {
    Camera::look_at(DVec3::from_array(eye), DVec3::from_array(target), WIDTH, HEIGHT)
}

fn render(gpu: &Gpu, location: &str, cam: Option<Camera>, settings: RenderSettings) -> Still {
    let options = StillOptions { width: WIDTH, height: HEIGHT, settings, ..StillOptions::default() };
    let camera = |m: &Metadata| cam.unwrap_or_else(|| default_camera(m, WIDTH, HEIGHT));
    render_still(gpu, Origin::parse(location).unwrap(), camera, &options).unwrap()
}

/// Lavapipe vs llvmpipe-GL and debug vs release builds differ by at most 1/255 on a few
/// pixels (PLATFORM.md); allowed here: mean absolute channel difference <= 0.5/255 and at
/// most 0.5 % of pixels off by more than 8/255 — a shifted LOD ring, a missing tile or a
/// crack breaks both.
const TOLERANCE: golden::Tolerance = golden::Tolerance { mean: 0.5, pixel: 8, off_share: 0.005 };

fn assert_golden(name: &str, still: &Still) {
    golden::assert_golden(name, still.width, still.height, &still.rgba, TOLERANCE);
}

#[test]
fn golden_views_of_a_real_dem() {
    let Some(gpu) = gpu() else { return };
    let archive = dem_archive().to_str().unwrap().to_owned();
    let lit = RenderSettings::default();
    // High altitude: the whole dataset (the default oblique framing).
    let whole = render(gpu, &archive, None, lit);
    assert_golden("tamalpais-whole", &whole);
    // Close to the ground on the southern slopes, looking north up the mountain.
    let close = render(gpu, &archive, Some(camera([4300.0, 750.0, 5600.0], [4700.0, 550.0, 3300.0])), lit);
    assert_eq!(close.frame.levels.0, 0, "the finest mesh level is drawn near the eye");
    assert_golden("tamalpais-close", &close);
    // Grazing across the whole crop from its southern edge: several LOD rings.
    let grazing = render(gpu, &archive, Some(camera([2200.0, 650.0, 9200.0], [5000.0, 350.0, 2500.0])), lit);
    assert!(grazing.frame.levels.1 >= grazing.frame.levels.0 + 2, "rings {:?}", grazing.frame.levels);
    assert_golden("tamalpais-grazing", &grazing);
    let with_lods = render(
        gpu,
        &archive,
        Some(camera([2200.0, 650.0, 9200.0], [5000.0, 350.0, 2500.0])),
        RenderSettings { lod_colours: true, wireframe: true, ..lit },
    );
    assert_golden("tamalpais-grazing-lods", &with_lods);
    // Over a sparse area: the east half lacks its two finest LODs; coverage falls back.
    let dir = tempfile::tempdir().unwrap();
    let sparse = sparse_archive(dir.path());
    let over_sparse =
        render(gpu, sparse.to_str().unwrap(), Some(camera([5200.0, 1400.0, 7000.0], [5600.0, 300.0, 4000.0])), lit);
    assert!(over_sparse.stream.missing > 0, "the sparse tiles were looked for and found missing");
    assert_golden("tamalpais-sparse", &over_sparse);
}

#[test]
fn mmap_and_http_give_identical_images() {
    let Some(gpu) = gpu() else { return };
    let archive = dem_archive();
    let cam = camera([2200.0, 650.0, 9200.0], [5000.0, 350.0, 2500.0]);
    let from_file = render(gpu, archive.to_str().unwrap(), Some(cam), RenderSettings::default());
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(archive, dir.path().join("tamalpais.tspack")).unwrap();
    let state = common::state(dir.path());
    let (addr, server) = runtime.block_on(support::serve(terrastream_server::app(state), "127.0.0.1:0"));
    let from_http = render(gpu, &format!("http://{addr}/tamalpais.tspack"), Some(cam), RenderSettings::default());
    let from_endpoint = render(gpu, &format!("http://{addr}/tamalpais"), Some(cam), RenderSettings::default());
    server.abort();
    assert!(from_http.stream.requests > 0);
    assert!(from_file.rgba == from_http.rgba, "mmap and HTTP range renders differ");
    assert!(from_file.rgba == from_endpoint.rgba, "mmap and tile-endpoint renders differ");
}

/// Black background, white terrain: any background pixel below the terrain's upper
/// silhouette in a column is a hole in the mesh.
#[test]
fn morphing_leaves_no_cracks() {
    let Some(gpu) = gpu() else { return };
    let archive = dem_archive().to_str().unwrap().to_owned();
    let flat = RenderSettings { shading: Shading::Flat, patch: 8, ..RenderSettings::default() };
    // Low over the land looking north-east across the mountain: many rings, morphing.
    for (i, (eye, target)) in
        [([4800.0, 330.0, 8600.0], [6500.0, 500.0, 2000.0]), ([6000.0, 900.0, 7500.0], [5000.0, 300.0, 3000.0])]
            .into_iter()
            .enumerate()
    {
        let still = render(gpu, &archive, Some(camera(eye, target)), flat);
        std::fs::create_dir_all(repo().join("target/render-tests")).unwrap();
        golden::write_png(
            &repo().join(format!("target/render-tests/cracks-{i}.png")),
            still.width,
            still.height,
            &still.rgba,
        );
        assert!(still.frame.levels.1 > still.frame.levels.0, "several mesh levels in view");
        let (w, h) = (still.width as usize, still.height as usize);
        let white = |x: usize, y: usize| still.rgba[(y * w + x) * 4] > 127;
        let mut terrain = 0;
        let mut holes = Vec::new();
        for x in 0..w {
            let Some(top) = (0..h).find(|&y| white(x, y)) else { continue };
            for y in top..h {
                if white(x, y) {
                    terrain += 1;
                } else {
                    holes.push((x, y));
                }
            }
        }
        assert!(terrain > w * h / 3, "view {i}: the terrain fills the lower image ({terrain} px)");
        assert!(
            holes.is_empty(),
            "view {i}: {} background pixels inside the terrain, e.g. {:?}",
            holes.len(),
            &holes[..holes.len().min(8)]
        );
    }
}

#[test]
fn hud_text_lands_in_the_top_left_corner() {
    use terrastream_client::render::gpu::{OFFSCREEN_FORMAT, Offscreen, render_pass};
    use terrastream_client::render::hud::Hud;
    let Some(gpu) = gpu() else { return };
    let target = Offscreen::new(&gpu.device, 200, 100);
    let mut hud = Hud::new(&gpu.device, OFFSCREEN_FORMAT);
    hud.set_text(&gpu.queue, &["fps 60".to_owned(), "tiles 12".to_owned()], (200, 100), 1);
    render_pass(&gpu.device, &gpu.queue, &target.colour_view(), &target.depth_view(), wgpu::Color::BLACK, |pass| {
        hud.draw(pass);
    });
    let rgba = target.read_rgba(&gpu.device, &gpu.queue).unwrap();
    let white = |x: usize, y: usize| rgba[(y * 200 + x) * 4] == 255;
    let inside = (0..40).flat_map(|y| (0..80).map(move |x| (x, y))).filter(|&(x, y)| white(x, y)).count();
    let outside = (0..100)
        .flat_map(|y| (0..200).map(move |x| (x, y)))
        .filter(|&(x, y)| (x >= 80 || y >= 40) && white(x, y))
        .count();
    assert!(inside > 50, "glyph pixels drawn: {inside}");
    assert_eq!(outside, 0);
}
