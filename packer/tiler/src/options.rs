//! What the tiler is asked to make: options, texture input and formats.

use terrastream_format::{PayloadCompression, TileFormat};

use crate::raster::ImageSource;

/// How to store elevation samples.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ElevationStorage {
    /// Quantized u16 when the range allows a step of at most 1/16 unit, else f32.
    #[default]
    Auto,
    /// Quantized u16.
    U16,
    /// f32.
    F32,
}

/// Options of [`crate::tile_terrain`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileOptions {
    /// Samples per tile edge, borders excluded.
    pub tile_size: u32,
    /// Samples copied from the neighbours on each side.
    pub border: u8,
    /// Sample storage.
    pub storage: ElevationStorage,
}

impl Default for TileOptions {
    fn default() -> Self {
        Self { tile_size: 256, border: 1, storage: ElevationStorage::Auto }
    }
}

/// One shard of a sharded tile run (`tile --shard I/N --split-lod K`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShardSpec {
    /// This shard, 0-based.
    pub index: u32,
    /// Shards in the run.
    pub count: u32,
    /// The last LOD shards make (each layer's at most its coarsest); None: the coarsest
    /// LOD with at least two rows of tiles per shard.
    pub split_lod: Option<u8>,
    /// Per layer, where the bands of the run begin and end (`count + 1` rows of tiles at
    /// the layer's split LOD), as a shard plan gives them ([`crate::ShardPlan`]); None:
    /// cut here, balancing the source's samples with data (which a shard given only its
    /// part of the inputs cannot do as the others do).
    pub cuts: Option<Vec<Vec<u32>>>,
}

/// How texture tiles are stored.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TextureFormat {
    /// Lossless PNG (RGB when opaque): exact, what browsers decode.
    #[default]
    Png,
    /// JPEG at a quality of 1..=100: smallest over a network; no alpha (holes turn black).
    Jpeg(u8),
    /// Lossless WebP.
    Webp,
    /// BC1 blocks + zstd: 4 bits a texel on the GPU, cut-out alpha; no CPU decode.
    Bc1,
    /// BC7 blocks + zstd: 8 bits a texel on the GPU, smooth alpha; no CPU decode.
    Bc7,
}

impl TextureFormat {
    /// Decoded exactly as encoded (PNG, WebP): what the levels above a shard's split LOD
    /// are made from.
    pub(crate) fn lossless(self) -> bool {
        matches!(self, Self::Png | Self::Webp)
    }

    /// The format a layer's stored tiles of `format` decode back from exactly: None for a
    /// lossy one (or one that is not imagery).
    pub(crate) fn decodable(format: TileFormat) -> Option<Self> {
        match format {
            TileFormat::Png => Some(Self::Png),
            TileFormat::Webp => Some(Self::Webp),
            _ => None,
        }
    }

    /// The format's name in messages.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Png => "PNG",
            Self::Jpeg(_) => "JPEG",
            Self::Webp => "WebP",
            Self::Bc1 => "BC1",
            Self::Bc7 => "BC7",
        }
    }

    pub(crate) fn tile_format(self) -> TileFormat {
        match self {
            Self::Png => TileFormat::Png,
            Self::Jpeg(_) => TileFormat::Jpeg,
            Self::Webp => TileFormat::Webp,
            Self::Bc1 => TileFormat::Bc1,
            Self::Bc7 => TileFormat::Bc7,
        }
    }

    pub(crate) fn compression(self) -> PayloadCompression {
        match self {
            Self::Bc1 | Self::Bc7 => PayloadCompression::Zstd,
            _ => PayloadCompression::None,
        }
    }

    /// Typical stored bytes per texel (for `--dry-run`'s estimate).
    pub(crate) fn typical_bytes_per_texel(self) -> f64 {
        match self {
            Self::Png | Self::Webp => 1.8,
            Self::Jpeg(_) => 0.3,
            Self::Bc1 => 0.4,
            Self::Bc7 => 0.8,
        }
    }
}

/// The texture input of [`crate::tile_terrain`].
#[derive(Clone, Copy)]
pub struct TextureInput<'a> {
    /// The image. With elevation it is stretched over the elevation's extent.
    pub source: &'a dyn ImageSource,
    /// Pixels per tile edge, borders excluded.
    pub tile_size: u32,
    /// Tile encoding.
    pub format: TextureFormat,
    /// Metres per pixel when there is no elevation to take the extent from.
    pub pixel_size: f64,
}
