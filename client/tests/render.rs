//! Rendering, on whatever adapter wgpu finds (the test command installs Mesa's lavapipe):
//! golden images of a real DEM crop (SRTM 1", Mt Tamalpais; public domain) from several
//! views, identical images from mmap and from HTTP, and a crack count on a flat-white render.
//!
//! Golden images live in `tests/golden/`. `TERRASTREAM_BLESS=1` (re)writes them; a missing
//! one fails. Without an adapter the tests fail unless `TERRASTREAM_ALLOW_NO_GPU=1`, which
//! skips them loudly (for machines without Mesa; never set on CI).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use glam::DVec3;
use terrastream_client::Surface;
use terrastream_client::render::gpu::Gpu;
use terrastream_client::render::renderer::{RenderSettings, Shading};
use terrastream_client::render::still::{Still, StillOptions, default_camera, render_still};
use terrastream_client::render::wgpu;
use terrastream_client::{Camera, Origin};
use terrastream_format::{Metadata, Reader};
use terrastream_pack::progress::Silent;
use terrastream_pack::{Writer, WriterOptions};
use terrastream_tiler::{TileOptions, read_geotiff, tile_elevation};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 200;

use terrastream_testkit::golden::repo;

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
            let raster = read_geotiff(&repo().join("packer/pack/data/srtm-tamalpais-320-public-domain.tif")).unwrap();
            let options = TileOptions { tile_size: 64, border: 1, ..TileOptions::default() };
            tile_elevation(&raster, "tamalpais", &path, options, &Silent::default()).unwrap();
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
    // These views are of the flat plate, posed in world units.
    let settings = RenderSettings { flat: true, ..settings };
    let options = StillOptions { width: WIDTH, height: HEIGHT, settings, ..StillOptions::default() };
    let camera = |m: &Metadata, s: &Surface| Ok(cam.unwrap_or_else(|| default_camera(m, s, WIDTH, HEIGHT)));
    render_still(gpu, Origin::parse(location).unwrap(), camera, &options).unwrap()
}

/// Lavapipe vs llvmpipe-GL and debug vs release builds differ by at most 1/255 on a few
/// pixels (PLATFORM.md); allowed here: mean absolute channel difference <= 0.5/255 and at
/// most 0.5 % of pixels off by more than 8/255 — a shifted LOD ring, a missing tile or a
/// crack breaks both.
const TOLERANCE: terrastream_testkit::golden::Tolerance =
    terrastream_testkit::golden::Tolerance { mean: 0.5, pixel: 8, off_share: 0.005 };

fn assert_golden(name: &str, still: &Still) {
    terrastream_testkit::golden::assert_golden(name, still.width, still.height, &still.rgba, TOLERANCE);
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
    let state = terrastream_testkit::server::state(dir.path());
    let (addr, server) =
        runtime.block_on(terrastream_testkit::server::serve_router(terrastream_server::app(state), "127.0.0.1:0"));
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
        terrastream_testkit::golden::write_png(
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

/// One BC1 block of a single colour (RGB565 endpoints equal, every index 0).
fn bc1_solid(rgb: [u8; 3]) -> [u8; 8] {
    let c = (u16::from(rgb[0] >> 3) << 11) | (u16::from(rgb[1] >> 2) << 5) | u16::from(rgb[2] >> 3);
    let [lo, hi] = c.to_le_bytes();
    [lo, hi, lo, hi, 0, 0, 0, 0]
}

/// One BC7 block of a single colour: mode 6, both endpoints the colour (7 bits + a shared
/// p-bit of 1 per endpoint), every index 0.
fn bc7_solid(rgb: [u8; 3]) -> [u8; 16] {
    let mut bits: u128 = 1 << 6; // mode 6
    let mut at = 7;
    for channel in [rgb[0], rgb[0], rgb[1], rgb[1], rgb[2], rgb[2], 255, 255] {
        bits |= u128::from(channel >> 1) << at;
        at += 7;
    }
    bits |= 0b11 << at; // p-bits
    bits.to_le_bytes()
}

/// BC1 and BC7 texture tiles go to the GPU as blocks, without a CPU decode: a 2x2-tile
/// layer of solid colours (red, green / blue, white) seen from straight above draws
/// those colours in its four quadrants, from a BC texture array.
#[test]
fn bc1_and_bc7_tiles_are_drawn_from_blocks() {
    use terrastream_format::{Layer, LayerKind, PayloadCompression, TileFormat, TileKey};
    let Some(gpu) = gpu() else { return };
    if !gpu.device.features().contains(wgpu::Features::TEXTURE_COMPRESSION_BC) {
        // Lavapipe (the test command's adapter) has BC; only another adapter lands here.
        assert!(gpu.info.driver != "llvmpipe", "lavapipe is expected to support BC textures");
        eprintln!("\n!!!!! SKIPPING BC TEST: {} has no BC texture support !!!!!\n", gpu.describe());
        return;
    }
    let colours = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]];
    for format in [TileFormat::Bc1, TileFormat::Bc7] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bc.tspack");
        let layer = Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format,
            compression: PayloadCompression::None,
            tile_resolution: 16,
            border: 0,
            num_x_tiles: 2,
            num_y_tiles: 2,
            num_lods: 2,
            tile_world_size: 100.0,
            elevation: None,
            extent: None,
        };
        let metadata = Metadata::new("bc", vec![layer]);
        let mut writer = Writer::create(&path, metadata.clone(), WriterOptions::default()).unwrap();
        let mut keys: Vec<TileKey> = (0..2).flat_map(|lod| metadata.layers[0].tiles_at(0, lod)).collect();
        keys.sort_by_key(|k| Writer::order_key(&metadata, *k).unwrap());
        for key in keys {
            let colour = if key.lod() == 1 { [128, 128, 128] } else { colours[(key.y() * 2 + key.x()) as usize] };
            let block: Vec<u8> =
                if format == TileFormat::Bc1 { bc1_solid(colour).to_vec() } else { bc7_solid(colour).to_vec() };
            writer.add(key, block.repeat(16)).unwrap();
        }
        writer.finish().unwrap();

        let cam = camera([100.0, 300.0, 100.001], [100.0, 0.0, 100.0]);
        let still = render(gpu, path.to_str().unwrap(), Some(cam), RenderSettings::default());
        let expected = if format == TileFormat::Bc1 {
            wgpu::TextureFormat::Bc1RgbaUnormSrgb
        } else {
            wgpu::TextureFormat::Bc7RgbaUnormSrgb
        };
        assert_eq!(still.texture_format, Some(expected), "{format:?} tiles went up as blocks");
        terrastream_testkit::golden::write_png(
            &repo().join(format!("target/render-tests/bc-{format:?}.png")),
            still.width,
            still.height,
            &still.rgba,
        );
        // Quadrant centres: screen up is north (-z), so tile (0,0) is top left.
        let pixel = |fx: f64, fy: f64| {
            let (x, y) = ((fx * f64::from(WIDTH)) as usize, (fy * f64::from(HEIGHT)) as usize);
            let i = (y * WIDTH as usize + x) * 4;
            [i32::from(still.rgba[i]), i32::from(still.rgba[i + 1]), i32::from(still.rgba[i + 2])]
        };
        let [tl, tr, bl, br] = [pixel(0.4, 0.35), pixel(0.6, 0.35), pixel(0.4, 0.65), pixel(0.6, 0.65)];
        let dominant = |p: [i32; 3], c: usize| (0..3).all(|o| o == c || p[c] > p[o] + 60);
        assert!(dominant(tl, 0), "{format:?}: red tile drawn as {tl:?}");
        assert!(dominant(tr, 1), "{format:?}: green tile drawn as {tr:?}");
        assert!(dominant(bl, 2), "{format:?}: blue tile drawn as {bl:?}");
        assert!(
            br.iter().all(|&c| c > 150) && br.iter().max().unwrap() - br.iter().min().unwrap() < 40,
            "{format:?}: white tile drawn as {br:?}"
        );
    }
}

/// A terrain 1048 km on a side whose tiles are all alike (heights periodic with the
/// tile size, at every LOD): the same view near the origin and 1000 km away must give the
/// same picture. With absolute f32 positions the far view would be quantized to 6 cm
/// steps and its texture and height lookups worse: camera-relative coordinates keep it
/// exact.
#[test]
fn a_view_1000_km_out_matches_the_same_view_near_the_origin() {
    use terrastream_format::{ElevationEncoding, ElevationScheme, Layer, LayerKind, PayloadCompression, TileFormat};
    let Some(gpu) = gpu() else { return };
    const GRID: u32 = 256;
    const RES: u32 = 64;
    const SPACING: f64 = 64.0;
    let tile = f64::from(RES) * SPACING; // 4096 m
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("huge.tspack");
    let layer = Layer {
        name: "elevation".into(),
        kind: LayerKind::Elevation,
        format: TileFormat::RawF32,
        compression: PayloadCompression::Zstd,
        tile_resolution: RES,
        border: 1,
        num_x_tiles: GRID,
        num_y_tiles: GRID,
        num_lods: terrastream_format::levels_to_one(GRID),
        tile_world_size: tile,
        elevation: Some(ElevationEncoding { scheme: ElevationScheme::Float32, scale: 1.0, offset: 0.0, nodata: None }),
        extent: None,
    };
    let mut metadata = Metadata::new("huge", vec![layer]);
    metadata.terrain.min_elevation = 0.0;
    metadata.terrain.max_elevation = 400.0;
    metadata.terrain.displacement = 400.0;
    metadata.terrain.elevation_range = 400.0;
    metadata.terrain.base_tile_size = SPACING;
    let height = |x: f64, z: f64| {
        let (u, v) = (x / tile * std::f64::consts::TAU, z / tile * std::f64::consts::TAU);
        200.0 + 120.0 * u.sin() * v.cos() + 40.0 * (3.0 * u + 1.0).sin() * (2.0 * v).sin()
    };
    // Every tile of a LOD has the same samples: one payload per LOD.
    let payloads: Vec<Vec<u8>> = (0..metadata.layers[0].num_lods)
        .map(|lod| {
            let step = SPACING * f64::from(lod).exp2();
            let mut raw = Vec::new();
            for j in 0..RES + 2 {
                for i in 0..RES + 2 {
                    let h = height((f64::from(i) - 0.5) * step, (f64::from(j) - 0.5) * step);
                    raw.extend_from_slice(&(h as f32).to_le_bytes());
                }
            }
            terrastream_pack::zstd_compress(&raw, 3).unwrap()
        })
        .collect();
    let layer = &metadata.layers[0];
    let mut keys: Vec<_> = (0..layer.num_lods).flat_map(|lod| layer.tiles_at(0, lod)).collect();
    keys.sort_by_key(|k| Writer::order_key(&metadata, *k).unwrap());
    let mut writer = Writer::create(&path, metadata.clone(), WriterOptions::default()).unwrap();
    for key in keys {
        writer.add_stored(key, payloads[usize::from(key.lod())].clone()).unwrap();
    }
    writer.finish().unwrap();

    // Low over the ground, looking down the slope: 2^7 tiles apart, so every quadtree
    // node of up to 128 tiles lines up the same way around both eyes.
    let view = |tx: f64| {
        let o = tx * tile;
        camera([o + 1300.0, 420.0, o + 2100.0], [o + 1700.0, 180.0, o + 1500.0])
    };
    let near = render(gpu, path.to_str().unwrap(), Some(view(64.0)), RenderSettings::default());
    let far = render(gpu, path.to_str().unwrap(), Some(view(192.0)), RenderSettings::default());
    assert!(192.0 * tile > 780_000.0 && GRID as f64 * tile > 1_000_000.0);
    let out = repo().join("target/render-tests");
    std::fs::create_dir_all(&out).unwrap();
    terrastream_testkit::golden::write_png(&out.join("precision-near.png"), near.width, near.height, &near.rgba);
    terrastream_testkit::golden::write_png(&out.join("precision-far.png"), far.width, far.height, &far.rgba);
    let sky = near.rgba.chunks_exact(4).filter(|p| p[..3] == near.rgba[..3]).count();
    assert!(sky < (WIDTH * HEIGHT / 2) as usize, "the view shows the terrain");
    let (mean, off) = terrastream_testkit::golden::difference(&near.rgba, &far.rgba, 8);
    assert!(
        mean <= 0.5 && off * 200 <= (WIDTH * HEIGHT) as usize,
        "the view 786 km out differs from the same view near the origin: mean {mean:.3}/255, {off} pixels off by > 8/255 \
         (target/render-tests/precision-*.png)"
    );
}

/// Texture LODs beyond 16 (the original engine stopped at 12): a layer 2^18 tiles wide
/// (19 LODs) whose 4x4 tiles in one corner exist at every LOD, each LOD one colour.
/// Looking straight down at a point that LOD l covers and LOD l - 1 does not, from an
/// altitude where the pixels want l - 1 (half a texel of l per pixel), the picture shows
/// LOD l: each of LODs 0..=16 is resident, found through the page table and drawn.
#[test]
fn seventeen_texture_lods_are_each_drawn() {
    use terrastream_format::{Layer, LayerKind, PayloadCompression, TileFormat, TileKey};
    let Some(gpu) = gpu() else { return };
    if !gpu.device.features().contains(wgpu::Features::TEXTURE_COMPRESSION_BC) {
        eprintln!("\n!!!!! SKIPPING: {} has no BC texture support !!!!!\n", gpu.describe());
        return;
    }
    const LODS: u8 = 19;
    const SHOWN: u8 = 17;
    // Colours with channels in {0, 128, 255} and at least one 255: distinct in hue and
    // saturation, so the lighting (one factor for the whole flat view) cannot confuse them.
    let palette: Vec<[u8; 3]> = (0..27u8)
        .map(|i| [i % 3, i / 3 % 3, i / 9].map(|c| [0u8, 128, 255][usize::from(c)]))
        .filter(|c| c.contains(&255))
        .take(usize::from(LODS))
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lods.tspack");
    let layer = Layer {
        name: "texture".into(),
        kind: LayerKind::Texture,
        format: TileFormat::Bc1,
        compression: PayloadCompression::None,
        tile_resolution: 4,
        border: 0,
        num_x_tiles: 1 << 18,
        num_y_tiles: 1 << 18,
        num_lods: LODS,
        tile_world_size: 4.0, // texels of 1 m at LOD 0
        elevation: None,
        extent: None,
    };
    let metadata = Metadata::new("lods", vec![layer]);
    let mut keys: Vec<TileKey> =
        (0..LODS).flat_map(|lod| (0..16).filter_map(move |i| TileKey::new(0, lod, i % 4, i / 4).ok())).collect();
    keys.retain(|k| u64::from(k.x()) < 1 << (18 - k.lod()) && u64::from(k.y()) < 1 << (18 - k.lod()));
    keys.sort_by_key(|k| Writer::order_key(&metadata, *k).unwrap());
    let mut writer = Writer::create(&path, metadata, WriterOptions::default()).unwrap();
    for key in keys {
        writer.add(key, bc1_solid(palette[usize::from(key.lod())]).to_vec()).unwrap();
    }
    writer.finish().unwrap();

    let settings = RenderSettings { fog_density: Some(0.0), ..RenderSettings::default() };
    let mut seen = Vec::new();
    for lod in 0..SHOWN {
        // Footprint of a centre pixel: 2 h tan 30° / HEIGHT; texels at LOD l are 2^l m,
        // tiles 4 * 2^l m: LOD l covers [0, 16 * 2^l] and LOD l - 1 [0, 8 * 2^l].
        let texel = f64::from(lod).exp2();
        let h = texel * 0.5 * f64::from(HEIGHT) / (2.0 * 30f64.to_radians().tan());
        let centre = 12.0 * texel;
        let cam = camera([centre, h, centre + h * 1e-6], [centre, 0.0, centre]);
        let still = render(gpu, path.to_str().unwrap(), Some(cam), settings);
        let i = ((HEIGHT as usize / 2) * WIDTH as usize + WIDTH as usize / 2) * 4;
        let p = [0, 1, 2].map(|c| f64::from(still.rgba[i + c]));
        let max = p.iter().copied().fold(1.0, f64::max);
        let nearest = (0..palette.len())
            .min_by(|&a, &b| {
                let d = |k: usize| (0..3).map(|c| (p[c] / max - f64::from(palette[k][c]) / 255.0).powi(2)).sum::<f64>();
                d(a).total_cmp(&d(b))
            })
            .unwrap();
        seen.push((lod, nearest, p));
    }
    let wrong: Vec<_> = seen.iter().filter(|(lod, nearest, _)| usize::from(*lod) != *nearest).collect();
    assert!(wrong.is_empty(), "LOD drawn at the centre vs expected: {wrong:?}");
}

/// A texture-only archive (no elevation layer) whose metadata puts the ground at 3 000 m,
/// 2 km across: once drawn at height 0 while the default view looked at 3 000 m, which
/// left a sky-only picture. It is drawn flat at its minimum elevation, textured, framed.
#[test]
fn a_texture_only_archive_draws_flat_at_its_minimum_elevation() {
    let Some(gpu) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let path = texture_only_archive(dir.path(), None);

    let still = render(gpu, path.to_str().unwrap(), None, RenderSettings::default());
    assert!(still.frame.patches > 0 && !still.frame.drew_nothing_in_view(), "{:?}", still.frame);
    assert_eq!(still.stream.tiles_fetched, 5, "{:?}", still.stream);
    // Every LOD-0 colour shows: the finest texture is drawn over the whole terrain.
    for colour in TILE_COLOURS {
        assert!(pixels_of(&still, colour) > 300, "colour {colour:?} not drawn");
    }
    assert_golden("texture-only-flat", &still);
}

/// The colours of the LOD-0 tiles of [`texture_only_archive`], by x + 2 y.
const TILE_COLOURS: [[u8; 3]; 4] = [[230, 60, 40], [40, 200, 60], [50, 80, 230], [230, 210, 40]];

/// Pixels of `still` near `colour`.
fn pixels_of(still: &Still, colour: [u8; 3]) -> usize {
    still.rgba.chunks_exact(4).filter(|p| p[..3].iter().zip(colour).all(|(a, b)| a.abs_diff(b) < 60)).count()
}

/// Nothing is drawn past where the archive says its data ends, though its tiles hold
/// pixels there (the grid is rounded up to whole tiles).
#[test]
fn nothing_is_drawn_past_the_data_extent() {
    let Some(gpu) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let whole = texture_only_archive(dir.path(), None);
    let cut = texture_only_archive(dir.path(), Some([1500.0, 1500.0]));
    // Both seen as the default view frames the whole grid.
    let cam = default_camera(Reader::open_mmap(&whole).unwrap().metadata(), &Surface::Flat, WIDTH, HEIGHT);
    // No haze: it follows the extent.
    let settings = RenderSettings { fog_density: Some(0.0), ..RenderSettings::default() };
    let (a, b) = [whole, cut].map(|p| render(gpu, p.to_str().unwrap(), Some(cam), settings)).into();
    // Tile (0, 0) lies inside the data; tile (1, 1) has only its north-west quarter there.
    let share = |k: usize| pixels_of(&b, TILE_COLOURS[k]) as f64 / pixels_of(&a, TILE_COLOURS[k]).max(1) as f64;
    assert!(pixels_of(&a, TILE_COLOURS[3]) > 1000, "tile (1, 1) is drawn whole without the extent");
    assert!((share(0) - 1.0).abs() < 0.02, "tile (0, 0): {:.3} of it drawn", share(0));
    // Its nearer three quarters cut, seen from the south: under a quarter of it on screen.
    assert!((0.08..0.3).contains(&share(3)), "tile (1, 1): {:.3} of it drawn", share(3));
}

/// A texture-only archive of 2 x 2 tiles of 1 km, a colour each at LOD 0 (checkered with
/// dark squares), at 3 000 m; `data_extent` as given.
fn texture_only_archive(dir: &Path, data_extent: Option<[f64; 2]>) -> PathBuf {
    use terrastream_format::TileKey;
    let path = dir.join(format!("texture-only-{}.tspack", data_extent.is_some()));
    let layer = terrastream_testkit::archives::png_texture_layer((2, 2), 2, 1000.0);
    let mut metadata = Metadata::new("texture-only", vec![layer]);
    metadata.terrain.min_elevation = 3000.0;
    metadata.terrain.max_elevation = 3000.0;
    metadata.terrain.data_extent = data_extent;
    let tile = |rgb: [u8; 3]| terrastream_testkit::archives::checkered_png(64, rgb, [20; 3]);
    let mut keys = vec![TileKey::new(0, 1, 0, 0).unwrap()];
    keys.extend((0..4).map(|i| TileKey::new(0, 0, i % 2, i / 2).unwrap()));
    keys.sort_by_key(|k| Writer::order_key(&metadata, *k).unwrap());
    let mut writer = Writer::create(&path, metadata, WriterOptions::default()).unwrap();
    for key in keys {
        let colour = TILE_COLOURS[(key.x() + 2 * key.y()) as usize];
        writer.add(key, tile(if key.lod() == 1 { [128; 3] } else { colour })).unwrap();
    }
    writer.finish().unwrap();
    path
}
