//! The whole Earth beyond an archive's data: a picture of continents, oceans and ice
//! (`client/data/earth.webp`, 2048 x 1024, equirectangular: Natural Earth II with its
//! shaded relief, public domain, as CesiumJS ships it for its own globe; joined by
//! `scripts/make-earth.sh`) built into the binary and the webplayer, drawn on the ground
//! the sky pass shows where the terrain is not. Its alpha holds the ground's heights above
//! the sea (SRTM30's, as KDE Marble's "Atlas" theme ships them: public domain), on which
//! the sky pass raises that ground.

use super::wgpu;

/// The picture, as committed (496 KiB: 171 of colour, 325 of heights).
const EARTH_WEBP: &[u8] = include_bytes!("../../data/earth.webp");

/// Its size in pixels.
const SIZE: (u32, u32) = (2048, 1024);

/// Mip levels down to 1 x 1... of the shorter side (the picture's 2:1 kept to 2 x 1).
const LEVELS: u32 = 11;

/// The picture's texture, sRGB with its mip chain; written by [`write_earth`].
pub(super) fn earth_texture(device: &wgpu::Device) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("texture.earth"),
        size: wgpu::Extent3d { width: SIZE.0, height: SIZE.1, depth_or_array_layers: 1 },
        mip_level_count: LEVELS,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba8UnormSrgb,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    })
}

/// The picture's RGBA pixels (None if the built-in bytes do not decode, which a test
/// rules out).
fn pixels() -> Option<Vec<u8>> {
    let image = terrastream_tiles::Image::decode(terrastream_format::TileFormat::Webp, EARTH_WEBP).ok()?;
    ((image.width(), image.height()) == SIZE).then(|| image.rgba8())
}

/// The highest ground the alpha holds, in metres.
pub(super) const HIGHEST: f32 = 9000.0;

/// The side of the cells of [`highest_near`]'s grid, in the picture's pixels (2.8125°).
const CELL: u32 = 16;

/// The picture decoded, once per process: by a thread of its own from the first renderer
/// that draws it ([`start_decoding`]), by a Web Worker ([`decoding_elsewhere`],
/// [`decoded_elsewhere`]), or else on the frame's thread at its first frame with a sky.
/// `None` inside: the built-in bytes did not decode (a test rules that out).
static DECODED: std::sync::OnceLock<Option<EarthPicture>> = std::sync::OnceLock::new();

/// Set while [`DECODED`] is being made elsewhere (a thread, a worker): frames draw the
/// plain ground until it is there, rather than decode it a second time.
static ELSEWHERE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// The whole-Earth picture decoded: its mip chain as the texture takes it (RGBA, sRGB
/// colours, heights in the alpha) and the highest ground in each cell of `CELL` x `CELL`
/// pixels (rows from the north, metres). About 70 ms of work on one core (release), which
/// a frame should not wait for.
#[derive(Debug, Clone, PartialEq)]
pub struct EarthPicture {
    /// The mip levels one after another, from the full picture down (`level_sizes`).
    levels: Vec<u8>,
    cells: Vec<f32>,
}

impl EarthPicture {
    /// Decodes the built-in picture and makes its mips and cells (None if its bytes do not
    /// decode, which a test rules out).
    #[must_use]
    pub fn decode() -> Option<Self> {
        let first = pixels()?;
        let cells = cells(&first);
        Some(Self { levels: mips(first), cells })
    }

    /// The picture as bytes (its levels, then its cells), to hand between threads that
    /// share no memory (a Web Worker's answer).
    #[must_use]
    pub fn to_wire(&self) -> Vec<u8> {
        let mut wire = self.levels.clone();
        wire.extend(self.cells.iter().flat_map(|c| c.to_le_bytes()));
        wire
    }

    /// The picture from [`EarthPicture::to_wire`]'s bytes, its levels kept where they
    /// are; None unless they are exactly as long as a picture's.
    #[must_use]
    pub fn from_wire(mut wire: Vec<u8>) -> Option<Self> {
        let levels: usize = level_sizes().map(|(w, h)| (4 * w * h) as usize).sum();
        let (columns, rows) = (SIZE.0 / CELL, SIZE.1 / CELL);
        if wire.len() != levels + 4 * (columns * rows) as usize {
            return None;
        }
        let cells = wire[levels..].chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        wire.truncate(levels);
        Some(Self { levels: wire, cells })
    }

    /// Each mip level's size and pixels, from the full picture down.
    fn levels(&self) -> impl Iterator<Item = ((u32, u32), &[u8])> {
        let mut rest = self.levels.as_slice();
        level_sizes().map(move |(w, h)| {
            let (level, after) = rest.split_at((4 * w * h) as usize);
            rest = after;
            ((w, h), level)
        })
    }
}

/// Starts decoding the picture on a thread of its own, once per process, where threads
/// exist (not in a browser's page: there a Web Worker does it). Until it is done, frames
/// draw the plain ground beyond the data and
/// [`earth_pending`](super::renderer::TerrainRenderer::earth_pending) holds.
pub(super) fn start_decoding() {
    #[cfg(not(target_arch = "wasm32"))]
    {
        use std::sync::atomic::Ordering;
        if DECODED.get().is_some() || ELSEWHERE.swap(true, Ordering::AcqRel) {
            return;
        }
        let spawned = std::thread::Builder::new().name("earth picture".into()).spawn(|| {
            // A panic in the decoder is a picture that did not decode, not a wait forever.
            let decoded = std::panic::catch_unwind(EarthPicture::decode).ok().flatten();
            let _ = DECODED.set(decoded);
        });
        if spawned.is_err() {
            ELSEWHERE.store(false, Ordering::Release);
        }
    }
}

/// Says that the picture is being decoded elsewhere (a Web Worker): frames draw the plain
/// ground beyond the data until [`decoded_elsewhere`] hands it in.
pub fn decoding_elsewhere() {
    ELSEWHERE.store(true, std::sync::atomic::Ordering::Release);
}

/// Hands in the picture decoded elsewhere; None when that failed: the first frame that
/// draws it then decodes it itself.
pub fn decoded_elsewhere(picture: Option<EarthPicture>) {
    if let Some(picture) = picture {
        let _ = DECODED.set(Some(picture));
    }
    ELSEWHERE.store(false, std::sync::atomic::Ordering::Release);
}

/// The decoded picture for a frame that draws it: decoded here unless it is being made
/// elsewhere; None while it is (the frame draws the plain ground).
fn picture() -> Option<&'static Option<EarthPicture>> {
    match DECODED.get() {
        Some(decoded) => Some(decoded),
        None if ELSEWHERE.load(std::sync::atomic::Ordering::Acquire) => None,
        None => Some(DECODED.get_or_init(EarthPicture::decode)),
    }
}

/// The highest ground within `reach` metres (along the ground) of longitude `lon` and
/// latitude `lat` (degrees; [`crate::globe::geodetic`]'s, turned to degrees): the highest
/// of the cells that reach touches, or the highest the alpha holds before the picture is
/// written. The sky pass marches its rays only below it.
pub(super) fn highest_near(lon: f64, lat: f64, reach: f64) -> f32 {
    let Some(Some(EarthPicture { cells, .. })) = DECODED.get() else {
        return HIGHEST;
    };
    let (columns, rows) = (SIZE.0 / CELL, SIZE.1 / CELL);
    let radius = (reach / 6_371_000.0).to_degrees();
    let cell = 180.0 / f64::from(rows);
    let row_of = |lat: f64| ((90.0 - lat) / cell).floor().clamp(0.0, f64::from(rows - 1));
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "clamped to the grid")]
    let (north, south) = (row_of(lat + radius) as u32, row_of(lat - radius) as u32);
    let mut highest = 0.0f32;
    for row in north..=south {
        // The widest of the row's parallels (the one nearest the pole) sets its reach east and west.
        let edge = (90.0 - f64::from(row) * cell).abs().max((90.0 - f64::from(row + 1) * cell).abs());
        let cos = edge.min(lat.abs() + radius).min(90.0).to_radians().cos();
        let half = if cos <= radius.to_radians().sin() || radius >= 90.0 { 180.0 } else { radius / cos };
        let span = if half >= 180.0 {
            0..columns as i64
        } else {
            #[allow(clippy::cast_possible_truncation, reason = "within a few turns")]
            let column = |lon: f64| ((lon + 180.0) / cell).floor() as i64;
            column(lon - half)..column(lon + half) + 1
        };
        for column in span {
            let c = column.rem_euclid(i64::from(columns));
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "within the grid")]
            let at = (row * columns) as usize + c as usize;
            highest = highest.max(cells[at]);
        }
    }
    highest
}

/// The ground's height above the sea (metres) that an alpha holds: 1 + 254 * sqrt(h /
/// 9000 m), so 0 and 1 are the sea (the shader's `earth_height` reads it so).
pub(super) fn height_of(alpha: u8) -> f32 {
    let s = f32::from(alpha.saturating_sub(1)) / 254.0;
    HIGHEST * s * s
}

/// The alpha that holds height `h` (metres above the sea).
#[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "rounded into 1..=255")]
fn alpha_of(h: f32) -> u8 {
    (1.0 + 254.0 * (h / HIGHEST).clamp(0.0, 1.0).sqrt()).round() as u8
}

/// The highest ground in each of [`highest_near`]'s cells, from the picture's RGBA pixels.
fn cells(rgba: &[u8]) -> Vec<f32> {
    let (columns, rows) = (SIZE.0 / CELL, SIZE.1 / CELL);
    let mut cells = vec![0.0f32; (columns * rows) as usize];
    for y in 0..SIZE.1 {
        for x in 0..SIZE.0 {
            let cell = &mut cells[((y / CELL) * columns + x / CELL) as usize];
            *cell = cell.max(height_of(rgba[(4 * (y * SIZE.0 + x) + 3) as usize]));
        }
    }
    cells
}

/// The sizes of the picture's mip levels, from the full picture down to 2 x 1.
fn level_sizes() -> impl Iterator<Item = (u32, u32)> {
    std::iter::successors(Some(SIZE), |&(w, h)| (w > 1 && h > 1).then_some((w / 2, h / 2))).take(LEVELS as usize)
}

/// The picture's mip chain from its pixels, one level after another: each level the mean
/// of 2 x 2 of the one above, its colours in linear light, its heights in metres.
fn mips(first: Vec<u8>) -> Vec<u8> {
    let to_linear: Vec<f32> = (0..=255u8).map(|v| super::settings::srgb_to_linear(f32::from(v) / 255.0)).collect();
    let mut levels = first;
    let mut above = 0;
    for (w, h) in level_sizes().skip(1) {
        let pw = 2 * w;
        let start = levels.len();
        let mut next = vec![0u8; (4 * w * h) as usize];
        let level = &levels[above..start];
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let at = |dx: u32, dy: u32| {
                        to_linear[usize::from(level[(4 * ((2 * y + dy) * pw + 2 * x + dx) + c) as usize])]
                    };
                    let mean = (at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1)) / 4.0;
                    next[(4 * (y * w + x) + c) as usize] = super::settings::linear_to_srgb_u8(mean);
                }
                let height = |dx: u32, dy: u32| height_of(level[(4 * ((2 * y + dy) * pw + 2 * x + dx) + 3) as usize]);
                let mean = (height(0, 0) + height(1, 0) + height(0, 1) + height(1, 1)) / 4.0;
                next[(4 * (y * w + x) + 3) as usize] = alpha_of(mean);
            }
        }
        levels.extend_from_slice(&next);
        above = start;
    }
    levels
}

/// Writes the picture and its mip chain into `texture` once it is decoded: None while it
/// is being decoded elsewhere (nothing written), Some(true) once written, Some(false)
/// when it does not decode (logged; the ground beyond the data stays plain).
pub(super) fn write_earth(queue: &wgpu::Queue, texture: &wgpu::Texture) -> Option<bool> {
    let decoded = picture()?;
    let Some(picture) = decoded else {
        tracing::error!("the built-in Earth picture does not decode: the ground beyond the data stays plain");
        return Some(false);
    };
    for (mip, ((w, h), level)) in picture.levels().enumerate() {
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: u32::try_from(mip).unwrap_or(0),
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            level,
            wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(4 * w), rows_per_image: Some(h) },
            wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
        );
    }
    Some(true)
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "test coordinates")]
mod tests {
    /// The picture's pixel at a longitude and latitude (degrees), offset by `dx`, `dy`.
    fn pixel(lon: f64, lat: f64, dx: isize, dy: isize) -> usize {
        let x = ((lon + 180.0) / 360.0 * 2048.0) as isize + dx;
        let y = ((90.0 - lat) / 180.0 * 1024.0) as isize + dy;
        (y * 2048 + x) as usize
    }

    #[test]
    fn the_built_in_picture_decodes_to_sea_land_and_ice() {
        let p = super::pixels().expect("earth.webp decodes");
        let at = |lon: f64, lat: f64| {
            let i = 4 * pixel(lon, lat, 0, 0);
            [i32::from(p[i]), i32::from(p[i + 1]), i32::from(p[i + 2])]
        };
        let sea = |[r, g, b]: [i32; 3]| b > r + 35 && b > g + 15 && b < 120;
        let green = |[r, g, b]: [i32; 3]| g > r + 30 && g > b + 30;
        let desert = |[r, g, b]: [i32; 3]| r + g > 2 * b + 40 && r > 150;
        let ice = |[r, g, b]: [i32; 3]| r.min(g).min(b) > 180 && b >= r;
        // The Pacific and the Atlantic, the Amazon, the Sahara, Greenland, Antarctica; north
        // up and east to the right (a picture flipped or turned would fail these).
        for (lon, lat) in [(-150.0, 0.0), (-30.0, 30.0), (160.0, -40.0)] {
            assert!(sea(at(lon, lat)), "{lon}, {lat}: {:?}", at(lon, lat));
        }
        assert!(green(at(-60.0, -5.0)), "{:?}", at(-60.0, -5.0));
        assert!(desert(at(10.0, 23.0)), "{:?}", at(10.0, 23.0));
        assert!(ice(at(-40.0, 72.0)) && ice(at(30.0, -80.0)), "{:?} {:?}", at(-40.0, 72.0), at(30.0, -80.0));
        assert!(!sea(at(10.0, 23.0)) && !ice(at(10.0, 23.0)) && !green(at(-150.0, 0.0)));
    }

    #[test]
    fn the_built_in_heights_raise_mountains_and_plateaus_and_keep_the_sea_at_zero() {
        let p = super::pixels().expect("earth.webp decodes");
        // The mean height over a box of the picture's pixels around a place.
        let mean = |lon: f64, lat: f64| {
            let box_ = (-2..=2).flat_map(|dy| (-2..=2).map(move |dx| pixel(lon, lat, dx, dy)));
            box_.map(|i| super::height_of(p[4 * i + 3])).sum::<f32>() / 25.0
        };
        // Oceans and a low coast: 0 (the sea surface, not its depths).
        for (lon, lat) in [(-150.0, 0.0), (-30.0, 30.0), (160.0, -40.0), (70.0, -20.0)] {
            assert_eq!(mean(lon, lat), 0.0, "{lon}, {lat}");
        }
        assert!(mean(5.5, 52.5) < 50.0, "the Netherlands: {}", mean(5.5, 52.5));
        // Tibet, the Altiplano, the Colorado Rockies, Greenland's and Antarctica's ice.
        for (lon, lat, low, high) in [
            (88.0, 32.0, 4000.0, 6000.0),
            (-68.0, -18.0, 3000.0, 5000.0),
            (-106.0, 39.5, 2000.0, 4000.0),
            (-40.0, 72.0, 2000.0, 3600.0),
            (30.0, -80.0, 2000.0, 4500.0),
        ] {
            let h = mean(lon, lat);
            assert!((low..high).contains(&h), "{lon}, {lat}: {h} m, not in {low}..{high}");
        }
        // Lowlands lower than highlands: the Amazon's basin below the Ethiopian highlands.
        assert!(mean(-60.0, -3.0) < 300.0 && mean(39.0, 9.0) > 1500.0, "{} {}", mean(-60.0, -3.0), mean(39.0, 9.0));
    }

    #[test]
    fn the_highest_ground_near_a_place_is_its_regions() {
        let _ = super::DECODED.set(super::EarthPicture::decode());
        let near = |lon: f64, lat: f64, km: f64| super::highest_near(lon, lat, km * 1000.0);
        // The mid-Pacific within 300 km: sea. Over the Ganges plain within 300 km: the
        // Himalaya. Within 500 km of Denver: the Rockies, not Tibet.
        assert_eq!(near(-150.0, 0.0, 300.0), 0.0);
        assert!(near(86.9, 26.7, 300.0) > 5000.0, "{}", near(86.9, 26.7, 300.0));
        let rockies = near(-105.0, 39.7, 500.0);
        assert!((2500.0..5000.0).contains(&rockies), "{rockies}");
        // Further reaches hold more: the whole Earth from 20 000 km, across the
        // antimeridian, and over a pole.
        assert!(near(-150.0, 0.0, 20_000.0) > 6000.0);
        assert!(near(179.0, 65.0, 400.0) >= near(-179.0, 65.0, 10.0));
        assert!(near(0.0, 89.0, 400.0) >= near(180.0, 88.0, 10.0));
        assert!(near(0.0, -89.0, 300.0) > 2000.0, "Antarctica's ice: {}", near(0.0, -89.0, 300.0));
    }

    /// The picture decoded elsewhere (a Web Worker) comes back whole from its bytes, and
    /// bytes of any other length are no picture.
    #[test]
    fn the_decoded_picture_comes_back_from_its_bytes() {
        let picture = super::EarthPicture::decode().expect("earth.webp decodes");
        let levels: Vec<_> = picture.levels().collect();
        assert_eq!(levels.len(), super::LEVELS as usize);
        assert_eq!(levels[0], ((2048, 1024), &picture.levels[..4 * 2048 * 1024]));
        assert_eq!(levels.iter().map(|(_, l)| l.len()).sum::<usize>(), picture.levels.len());
        // The last level, 2 x 1, is the mean of each half: land and sea, some height.
        let ((w, h), last) = levels[levels.len() - 1];
        assert_eq!((w, h, last.len()), (2, 1, 8));
        assert!(last[2] > 20 && last[3] > 1, "{last:?}");
        let wire = picture.to_wire();
        assert_eq!(super::EarthPicture::from_wire(wire.clone()).as_ref(), Some(&picture));
        assert!(super::EarthPicture::from_wire(wire[..wire.len() - 1].to_vec()).is_none());
        assert!(super::EarthPicture::from_wire([wire.as_slice(), &[0]].concat()).is_none());
        assert!(super::EarthPicture::from_wire(Vec::new()).is_none());
    }

    #[test]
    fn an_alpha_holds_a_height_within_its_step() {
        for h in [0.0f32, 1.0, 50.0, 500.0, 2000.0, 4500.0, 8848.0, 9000.0] {
            let back = super::height_of(super::alpha_of(h));
            // The step at h: 2 sqrt(9000 h) / 254, and under a metre near the sea.
            let step = 2.0 * (9000.0 * h).sqrt() / 254.0 + 1.0;
            assert!((back - h).abs() <= step, "{h} -> {back}");
        }
        assert_eq!(super::height_of(0), 0.0);
        assert_eq!(super::height_of(1), 0.0);
        assert_eq!(super::height_of(255), 9000.0);
    }
}
