//! The whole Earth beyond an archive's data: a picture of continents, oceans and ice
//! (`client/data/earth.webp`, 2048 x 1024, equirectangular: Natural Earth II with its
//! shaded relief, public domain, as CesiumJS ships it for its own globe; joined by
//! `scripts/make-earth.sh`) built into the binary and the webplayer, drawn on the ground
//! the sky pass shows where the terrain is not.

use super::wgpu;

/// The picture, as committed (171 KiB).
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

/// Writes the picture and its mip chain (each level the mean of 2 x 2 of the one above,
/// in linear light).
pub(super) fn write_earth(queue: &wgpu::Queue, texture: &wgpu::Texture) {
    let Some(mut level) = pixels() else {
        tracing::error!("the built-in Earth picture does not decode: the ground beyond the data stays plain");
        return;
    };
    let (mut w, mut h) = SIZE;
    let to_linear: Vec<f32> = (0..=255u8).map(|v| super::settings::srgb_to_linear(f32::from(v) / 255.0)).collect();
    for mip in 0..LEVELS {
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: mip,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            &level,
            wgpu::TexelCopyBufferLayout { offset: 0, bytes_per_row: Some(4 * w), rows_per_image: Some(h) },
            wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
        );
        if w == 1 || h == 1 {
            break;
        }
        let (nw, nh) = (w / 2, h / 2);
        let mut next = vec![255u8; (4 * nw * nh) as usize];
        for y in 0..nh {
            for x in 0..nw {
                for c in 0..3 {
                    let at = |dx: u32, dy: u32| {
                        to_linear[usize::from(level[(4 * ((2 * y + dy) * w + 2 * x + dx) + c) as usize])]
                    };
                    let mean = (at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1)) / 4.0;
                    next[(4 * (y * nw + x) + c) as usize] = super::settings::linear_to_srgb_u8(mean);
                }
            }
        }
        (level, w, h) = (next, nw, nh);
    }
}

#[cfg(test)]
#[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "test coordinates")]
mod tests {
    #[test]
    fn the_built_in_picture_decodes_to_sea_land_and_ice() {
        let p = super::pixels().expect("earth.webp decodes");
        let at = |lon: f64, lat: f64| {
            let x = ((lon + 180.0) / 360.0 * 2048.0) as usize;
            let y = ((90.0 - lat) / 180.0 * 1024.0) as usize;
            let i = 4 * (y * 2048 + x);
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
}
