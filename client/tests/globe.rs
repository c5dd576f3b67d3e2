//! The globe: a georeferenced archive is drawn on the WGS 84 ellipsoid. A world archive
//! seen whole is round; the horizon dips below the horizontal as geometry says it must;
//! `flat` keeps the plate. Rendered on lavapipe, measured on the pixels.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use terrastream_client::fly::Pose;
use terrastream_client::render::gpu::Gpu;
use terrastream_client::render::renderer::{RenderSettings, Shading};
use terrastream_client::render::still::{Still, StillOptions, default_camera, render_still, write_png};
use terrastream_client::{Camera, Origin, Surface};
use terrastream_format::{Georeference, Metadata, TileKey};
use terrastream_pack::{Writer, WriterOptions};

fn gpu() -> Option<&'static Gpu> {
    static GPU: OnceLock<Option<Gpu>> = OnceLock::new();
    GPU.get_or_init(|| match Gpu::headless() {
        Ok(gpu) => Some(gpu),
        Err(e) if std::env::var_os("TERRASTREAM_ALLOW_NO_GPU").is_some() => {
            eprintln!("\n!!!!! SKIPPING GLOBE TESTS: {e} (TERRASTREAM_ALLOW_NO_GPU is set) !!!!!\n");
            None
        }
        Err(e) => panic!("{e}: install mesa-vulkan-drivers, or set TERRASTREAM_ALLOW_NO_GPU=1 to skip"),
    })
    .as_ref()
}

/// Metres of the equator per degree (the world unit of a geographic archive is a metre
/// at the equator).
const EQUATOR_METRES_PER_DEGREE: f64 = 6_378_137.0 * std::f64::consts::PI / 180.0;

/// A texture-only archive of `tiles` LOD-0 tiles of 64 checkered pixels (a colour per
/// column of tiles) and every coarser LOD up to one tile, placed by `georeference`.
fn texture_world(
    name: &str,
    tiles: (u32, u32),
    tile_world_size: f64,
    georeference: Georeference,
) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(format!("{name}.tspack"));
    let lods = u8::try_from(tiles.0.max(tiles.1).next_power_of_two().trailing_zeros() + 1).unwrap();
    let layer = terrastream_testkit::archives::png_texture_layer(tiles, lods, tile_world_size);
    let mut metadata = Metadata::new(name, vec![layer]);
    metadata.georeference = Some(georeference);
    let mut keys: Vec<TileKey> = (0..lods)
        .flat_map(|lod| {
            let (w, h) = (tiles.0.div_ceil(1 << lod), tiles.1.div_ceil(1 << lod));
            (0..w * h).map(move |i| TileKey::new(0, lod, i % w, i / w).unwrap())
        })
        .collect();
    keys.sort_by_key(|k| Writer::order_key(&metadata, *k).unwrap());
    let mut writer = Writer::create(&path, metadata, WriterOptions::default()).unwrap();
    for key in keys {
        let colour = [[200, 60, 60], [60, 200, 60], [60, 60, 200], [200, 200, 60]][(key.x() % 4) as usize];
        writer.add(key, terrastream_testkit::archives::checkered_png(64, colour, [40; 3])).unwrap();
    }
    writer.finish().unwrap();
    (dir, path)
}

/// A texture-only world archive in EPSG:4326: 4 x 2 tiles of 90 degrees (written once per
/// test binary).
fn world_archive() -> &'static Path {
    static ARCHIVE: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let georeference = || Georeference {
        crs: Some("EPSG:4326".into()),
        origin: Some([-180.0, 90.0]),
        lat_lon_bounds: Some([-180.0, -90.0, 180.0, 90.0]),
        definition: Some("+proj=longlat +datum=WGS84 +no_defs".into()),
        scale: Some([1.0 / EQUATOR_METRES_PER_DEGREE; 2]),
    };
    &ARCHIVE.get_or_init(|| texture_world("world", (4, 2), 90.0 * EQUATOR_METRES_PER_DEGREE, georeference())).1
}

/// A texture-only world archive in Web Mercator (EPSG:3857): 2 x 2 tiles.
fn mercator_archive() -> &'static Path {
    static ARCHIVE: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let half = 20_037_508.342_789_244;
    let georeference = || {
        Georeference {
        crs: Some("EPSG:3857".into()),
        origin: Some([-half, half]),
        lat_lon_bounds: None,
        definition: Some(
            "+proj=merc +a=6378137 +b=6378137 +lat_ts=0 +lon_0=0 +x_0=0 +y_0=0 +k=1 +units=m +nadgrids=@null +wktext +no_defs"
                .into(),
        ),
        scale: Some([1.0, 1.0]),
    }
    };
    &ARCHIVE.get_or_init(|| texture_world("mercator", (2, 2), half, georeference())).1
}

fn render(
    path: &Path,
    width: u32,
    height: u32,
    settings: RenderSettings,
    camera: impl FnOnce(&Metadata, &Surface) -> Result<Camera, String>,
) -> Option<Still> {
    let gpu = gpu()?;
    let options = StillOptions { width, height, settings, ..StillOptions::default() };
    Some(render_still(gpu, Origin::parse(path.to_str().unwrap()).unwrap(), camera, &options).unwrap())
}

fn save(name: &str, still: &Still) {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("globe");
    std::fs::create_dir_all(&dir).unwrap();
    write_png(&dir.join(format!("{name}.png")), still.width, still.height, &still.rgba).unwrap();
}

fn lit(still: &Still, x: u32, y: u32) -> bool {
    let i = ((y * still.width + x) * 4) as usize;
    still.rgba[i..i + 3].iter().any(|&c| c > 16)
}

const FLAT_WHITE: RenderSettings = RenderSettings {
    elevation_slots: 64,
    texture_slots: 64,
    patch: 32,
    shading: Shading::Flat,
    wireframe: false,
    lod_colours: false,
    detail: 0.0,
    sun: glam::DVec3::Y,
    fog_density: None,
    sky: [0.0; 3],
    flat: false,
    atmosphere: false,
    earth: false,
};

/// The default view of a world archive is the whole Earth, and it is round: what is drawn
/// fills the ellipse inscribed in its bounding box, which is as wide as it is high.
#[test]
fn the_earth_is_round() {
    let Some(still) = render(world_archive(), 800, 600, FLAT_WHITE, |m, s| Ok(default_camera(m, s, 800, 600))) else {
        return;
    };
    save("round", &still);
    let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0, 0);
    for y in 0..still.height {
        for x in 0..still.width {
            if lit(&still, x, y) {
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
            }
        }
    }
    assert!(x1 > x0 && y1 > y0, "nothing drawn");
    let (w, h) = (f64::from(x1 - x0 + 1), f64::from(y1 - y0 + 1));
    assert!((w / h - 1.0).abs() <= 0.03, "the disc is {w} x {h} px");
    assert!(w > 300.0, "the Earth fills the frame: {w} px wide");
    let (cx, cy) = (f64::from(x0 + x1) * 0.5, f64::from(y0 + y1) * 0.5);
    let (mut inside, mut filled) = (0u32, 0u32);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (u, v) = ((f64::from(x) - cx) / (w * 0.5), (f64::from(y) - cy) / (h * 0.5));
            if u * u + v * v <= 1.0 {
                inside += 1;
                filled += u32::from(lit(&still, x, y));
            }
        }
    }
    let share = f64::from(filled) / f64::from(inside);
    assert!(share >= 0.95, "{share:.4} of the inscribed ellipse is drawn");
}

/// At 100 km and 10 km above the equator looking east, level, with a 60-degree vertical
/// field of view on 800 x 600: the horizon lies arccos(R / (R + h)) below the horizontal,
/// 10.1 and 3.2 degrees, rows 392 and 329 of the middle column.
#[test]
fn the_horizon_dips_as_geometry_says() {
    for (height, row) in [(100_000.0, 392.0), (10_000.0, 329.0)] {
        let pose = Pose::parse(&format!("0,0,{height}"), 90.0, 0.0).unwrap();
        let camera = |m: &Metadata, s: &Surface| {
            let (eye, target) = pose.eye_target(m, s)?;
            let mut camera = Camera::look_at(eye, target, 800, 600);
            camera.zenith = s.up(eye);
            Ok(camera)
        };
        let Some(still) = render(world_archive(), 800, 600, FLAT_WHITE, camera) else { return };
        save(&format!("horizon-{height}"), &still);
        let first = (0..still.height).find(|&y| lit(&still, 400, y)).expect("no ground in the middle column");
        let dip = (6_378_137.0f64 / (6_378_137.0 + height)).acos();
        let expected = 300.0 + dip.tan() / 30f64.to_radians().tan() * 300.0;
        assert!((expected - row).abs() < 0.6, "the geometry: {expected}");
        assert!(
            (f64::from(first) - expected).abs() <= 3.0,
            "at {height} m the horizon is at row {first}, geometry says {expected:.1}"
        );
    }
}

/// `flat` keeps the plate for a georeferenced archive: the world is a 2:1 sheet.
#[test]
fn flat_keeps_the_plate() {
    let settings = RenderSettings { flat: true, ..FLAT_WHITE };
    let Some(still) = render(world_archive(), 800, 600, settings, |m, s| {
        assert!(s.globe().is_none(), "flat asked: the plate");
        Ok(default_camera(m, s, 800, 600))
    }) else {
        return;
    };
    save("flat", &still);
    // Seen obliquely from the south, the sheet's far edge is straight: its top row of
    // lit pixels spans the same row across the middle half of the picture.
    let top = |x: u32| (0..still.height).find(|&y| lit(&still, x, y));
    let rows: Vec<u32> = (300..500).step_by(20).filter_map(top).collect();
    assert_eq!(rows.len(), 10, "the sheet spans the middle");
    assert!(rows.iter().max().unwrap() - rows.iter().min().unwrap() <= 1, "a straight far edge: {rows:?}");
}

/// Lit, with the atmosphere.
fn lit_settings(sun: glam::DVec3) -> RenderSettings {
    RenderSettings { shading: Shading::Lit, sun, atmosphere: true, ..FLAT_WHITE }
}

/// The direction towards a sun at `azimuth` (clockwise from north) and `elevation`.
fn sun_at(azimuth: f64, elevation: f64) -> glam::DVec3 {
    terrastream_client::globe::sun_direction(azimuth, elevation).unwrap()
}

fn posed(at: &str, heading: f64, pitch: f64) -> impl FnOnce(&Metadata, &Surface) -> Result<Camera, String> {
    let pose = Pose::parse(at, heading, pitch).unwrap();
    move |m: &Metadata, s: &Surface| {
        let (eye, target) = pose.eye_target(m, s)?;
        let mut camera = Camera::look_at(eye, target, 800, 600);
        camera.zenith = s.up(eye);
        Ok(camera)
    }
}

fn rgb(still: &Still, x: u32, y: u32) -> [f64; 3] {
    let i = ((y * still.width + x) * 4) as usize;
    [0, 1, 2].map(|k| f64::from(still.rgba[i + k]))
}

/// The mean colour of rows `y0..y1`.
fn band(still: &Still, y0: u32, y1: u32) -> [f64; 3] {
    let mut sum = [0.0; 3];
    for y in y0..y1 {
        for x in 0..still.width {
            let c = rgb(still, x, y);
            (0..3).for_each(|k| sum[k] += c[k]);
        }
    }
    sum.map(|v| v / f64::from((y1 - y0) * still.width))
}

/// From space the Earth has a blue limb: just outside the disc the air glows blue, far
/// from it space is black.
#[test]
fn from_space_the_limb_is_blue() {
    let default = |m: &Metadata, s: &Surface| Ok(default_camera(m, s, 800, 600));
    let Some(white) = render(world_archive(), 800, 600, FLAT_WHITE, default) else { return };
    let Some(sunlit) = render(world_archive(), 800, 600, lit_settings(sun_at(0.0, 90.0)), default) else { return };
    save("limb", &sunlit);
    // The disc's rightmost lit pixel on the middle row, from the flat render.
    let edge = (0..800).rev().find(|&x| lit(&white, x, 300)).unwrap();
    // The air is 100 km thick: 4 px here.
    let glow = (1..=4).map(|dx| rgb(&sunlit, edge + dx, 300)).max_by(|a, b| a[2].total_cmp(&b[2])).unwrap();
    assert!(glow[2] > 40.0 && glow[2] > glow[0] * 1.5, "the air just outside the disc: {glow:?}");
    let beyond = rgb(&sunlit, edge + 12, 300);
    assert!(beyond.iter().all(|&c| c < 3.0), "beyond the air, space: {beyond:?}");
    let space = rgb(&sunlit, 5, 5);
    assert!(space.iter().all(|&c| c < 3.0), "space is black: {space:?}");
}

/// Looking along the ground at 2 km with the sun high: the ground grows hazier towards the
/// horizon (its colour nearer the sky's there), and the sky is blue above, paler below.
#[test]
fn distant_ground_is_hazy_and_the_sky_blue() {
    let Some(still) =
        render(world_archive(), 800, 600, lit_settings(sun_at(0.0, 60.0)), posed("30,0,2000", 90.0, -5.0))
    else {
        return;
    };
    save("haze", &still);
    let horizon = (0..600).find(|&y| band(&still, y, y + 1)[1] > band(&still, 0, 1)[1] + 40.0).unwrap_or(300);
    let sky_low = band(&still, horizon.saturating_sub(12), horizon.saturating_sub(2));
    let sky_high = band(&still, 0, 10);
    assert!(sky_high[2] > sky_high[0] * 1.5, "the sky above is blue: {sky_high:?}");
    let distance = |a: [f64; 3], b: [f64; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt();
    let far = band(&still, horizon + 2, horizon + 12);
    let near = band(&still, 580, 600);
    assert!(
        distance(far, sky_low) < 0.5 * distance(near, sky_low),
        "far ground {far:?} and near {near:?} against the sky at the horizon {sky_low:?}"
    );
}

/// The sun: low in the east, the sky there is redder than with the sun high; set, the sky
/// is dark.
#[test]
fn the_sun_colours_the_sky() {
    let sky = |elevation: f64| {
        let settings = lit_settings(sun_at(90.0, elevation));
        render(world_archive(), 800, 600, settings, posed("0,0,100", 90.0, 10.0)).map(|s| {
            save(&format!("sun-{elevation}"), &s);
            band(&s, 200, 260)
        })
    };
    let (Some(high), Some(low), Some(set)) = (sky(60.0), sky(3.0), sky(-20.0)) else { return };
    let warmth = |c: [f64; 3]| c[0] / c[2].max(1.0);
    assert!(warmth(low) > warmth(high) * 1.3, "sunset {low:?} against noon {high:?}");
    let brightness = |c: [f64; 3]| c.iter().sum::<f64>();
    assert!(brightness(set) < 0.2 * brightness(high), "after sunset {set:?} against noon {high:?}");
}

/// Straight down on each pole from 20 000 km: a full disc, no hole where the grid's
/// meridians meet (geographic) or where Web Mercator's world ends at 85.05 degrees.
#[test]
fn the_poles_have_no_holes() {
    for (name, archive) in [("geographic", world_archive()), ("mercator", mercator_archive())] {
        for (pole, lat) in [("north", 90), ("south", -90)] {
            let at = format!("0,{lat},20000000");
            let camera = posed(&at, 0.0, -90.0);
            let Some(still) = render(archive, 800, 600, FLAT_WHITE, camera) else { return };
            save(&format!("pole-{name}-{pole}"), &still);
            for y in 290..310 {
                for x in 390..410 {
                    assert!(lit(&still, x, y), "{name}, {pole} pole: a hole at pixel ({x}, {y})");
                }
            }
            let drawn = (0..still.height).flat_map(|y| (0..still.width).map(move |x| (x, y)));
            let count = drawn.filter(|&(x, y)| lit(&still, x, y)).count();
            // The Earth's disc at 20 000 km fills about 86 px of radius here.
            assert!(count > 20_000, "{name}, {pole} pole: {count} pixels drawn");
        }
    }
}
