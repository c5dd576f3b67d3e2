//! The archive's JSON metadata document (FORMAT.md §3): layers and their grids and
//! encodings, the terrain/mesh parameters of the original engine, georeference, and the
//! original metadata fields kept verbatim.

use serde::{Deserialize, Serialize};

use crate::datum::VerticalDatum;
use crate::error::{Error, Result};
use crate::extent::LayerExtent;
use crate::key::{MAX_LAYERS, MAX_LODS, TileKey};

/// The metadata document.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metadata {
    /// Dataset name.
    #[serde(default)]
    pub name: String,
    /// Free text.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub description: String,
    /// Tile sets, in layer-index order (the index is the low 4 bits of a directory key).
    pub layers: Vec<Layer>,
    /// Elevation range and runtime mesh parameters.
    #[serde(default)]
    pub terrain: Terrain,
    /// Optional placement on the Earth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub georeference: Option<Georeference>,
    /// What the heights are measured from (absent: unknown, as older archives read).
    #[serde(default, skip_serializing_if = "VerticalDatum::is_unknown")]
    pub vertical_datum: VerticalDatum,
    /// Fields of an original-engine metadata text, in their order, values verbatim,
    /// including the ones this format has no field for.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub original_fields: Vec<OriginalField>,
    /// Set on one shard of a sharded tile run (`tile --shard I/N`): which part of the
    /// grid it holds. A merge of all N shards makes the levels above the split LODs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<Shard>,
    /// The elevation's inputs of a collection (inputs of different resolutions, each as
    /// deep as it reaches; docs/tiling.md, "Collections"), in the order given.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sources: Vec<SourceRecord>,
    /// Members this version does not know, kept on rewrite.
    #[serde(flatten)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// One input of a collection, as the archive records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SourceRecord {
    /// The input's file name.
    pub name: String,
    /// Its sample spacing in world metres.
    pub spacing: f64,
    /// The finest LOD it reaches.
    pub lod: u8,
    /// Its footprint's box in world units (min x, min z, max x, max z).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub world: Option<[f64; 4]>,
    /// The band, in samples of the finest level, across which it blends into the coarser
    /// data beneath (what an update adding a survey blends it with).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub blend: Option<u32>,
    /// The layer it feeds, when not the elevation (`"texture"` for imagery).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layer: Option<String>,
}

impl Metadata {
    /// The spacing in world metres of the finest collection input whose footprint holds
    /// world point (`x`, `z`): what a height there is surveyed at (None: not a collection,
    /// or no input there).
    #[must_use]
    pub fn source_spacing_at(&self, x: f64, z: f64) -> Option<f64> {
        (self.sources.iter())
            .filter(|s| s.layer.is_none())
            .filter(|s| s.world.is_some_and(|[x0, z0, x1, z1]| x >= x0 && x <= x1 && z >= z0 && z <= z1))
            .map(|s| s.spacing)
            .reduce(f64::min)
    }
}

/// One shard of a sharded tile run: tiles of every layer from LOD 0 up to that layer's
/// split LOD, in a band of the grid's tile rows; the levels above are made from the
/// shards' split-LOD tiles when they are merged (FORMAT.md §3.5).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    /// This shard, 0-based.
    pub index: u32,
    /// Shards in the run.
    pub count: u32,
    /// Per layer (in layer order): the last LOD this shard holds tiles of.
    pub split_lods: Vec<u8>,
    /// Per layer: the LOD-0 tile rows `[start, end)` whose tiles (and those above them
    /// up to the split LOD) this shard holds.
    pub tile_rows: Vec<[u32; 2]>,
}

/// What a layer holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LayerKind {
    /// RGB(A) imagery.
    Texture,
    /// Heights.
    Elevation,
    /// Surface normals.
    Normals,
    /// Material / classification map.
    Material,
    /// The lowest and highest height of each tile of an elevation layer with the same grid
    /// (format [`TileFormat::MinMaxF32`]), for culling and LOD decisions before the tile
    /// itself is loaded.
    HeightRange,
    /// Where the surface is water (sea, lakes, rivers): on the grid of the elevation layer
    /// it follows, each sample the fraction of water there, decoded by the layer's
    /// `elevation` encoding (0 land, 1 water; no data where the mask said nothing, which a
    /// reader takes from the heights' flat-sea rule instead). Format major 3.
    Water,
}

/// Encoding of each tile payload of a layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TileFormat {
    /// PNG file bytes.
    Png,
    /// JPEG file bytes.
    Jpeg,
    /// WebP file bytes.
    Webp,
    /// Row-major little-endian u16 samples, `(res + 2*border)^2` of them.
    RawU16,
    /// Row-major little-endian f32 samples.
    RawF32,
    /// BC1 (DXT1) blocks, ready for GPU upload.
    Bc1,
    /// BC7 blocks, ready for GPU upload.
    Bc7,
    /// Two little-endian f32: the lowest and highest height (world units) of the samples,
    /// borders included, of the tile with the same LOD, x and y in the elevation layer.
    MinMaxF32,
}

impl TileFormat {
    /// Usual file extension.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Png => "png",
            Self::Jpeg => "jpg",
            Self::Webp => "webp",
            Self::RawU16 => "u16",
            Self::RawF32 => "f32",
            Self::Bc1 => "bc1",
            Self::Bc7 => "bc7",
            Self::MinMaxF32 => "minmax",
        }
    }

    /// HTTP media type.
    pub fn media_type(self) -> &'static str {
        match self {
            Self::Png => "image/png",
            Self::Jpeg => "image/jpeg",
            Self::Webp => "image/webp",
            Self::RawU16 | Self::RawF32 | Self::Bc1 | Self::Bc7 | Self::MinMaxF32 => "application/octet-stream",
        }
    }

    /// Recognizes an image file by its first bytes.
    pub fn sniff(bytes: &[u8]) -> Option<Self> {
        if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
            Some(Self::Png)
        } else if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
            Some(Self::Jpeg)
        } else if bytes.len() >= 12 && &bytes[0..4] == b"RIFF" && &bytes[8..12] == b"WEBP" {
            Some(Self::Webp)
        } else {
            None
        }
    }
}

/// Extra compression applied to a payload on top of its format.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PayloadCompression {
    /// Stored as the format's bytes.
    #[default]
    None,
    /// One zstd frame around the format's bytes.
    Zstd,
    /// `raw_u16` only: the samples gradient-coded (each less the plane through its west,
    /// north and north-west neighbours, zigzagged, low bytes then high bytes), in one zstd
    /// frame; about half the bytes of `zstd` on terrain. Format major 2 (FORMAT.md §3.6).
    ZstdGradient,
}

impl PayloadCompression {
    /// The name FORMAT.md and the metadata give it.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Zstd => "zstd",
            Self::ZstdGradient => "zstd_gradient",
        }
    }
}

/// How pixel values of an elevation layer map to heights in world units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ElevationScheme {
    /// 8-bit gray: h = offset + v / 255 * scale.
    Gray8,
    /// Original engine's RGB thirds: v = R + G + B in 0..765, h = offset + v / 765 * scale.
    RgbThirds,
    /// Mapbox Terrain-RGB: h = -10000 + (R * 65536 + G * 256 + B) * 0.1.
    TerrainRgb,
    /// Terrarium: h = R * 256 + G + B / 256 - 32768.
    Terrarium,
    /// Quantized u16 samples: h = offset + v * scale.
    QuantizedU16,
    /// f32 samples are heights.
    Float32,
}

/// Elevation decoding parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ElevationEncoding {
    /// Value-to-height mapping.
    pub scheme: ElevationScheme,
    /// Scale of the mapping (see the scheme).
    #[serde(default = "one")]
    pub scale: f64,
    /// Offset of the mapping (see the scheme).
    #[serde(default)]
    pub offset: f64,
    /// Raw sample value meaning "no data".
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nodata: Option<f64>,
}

impl ElevationScheme {
    /// The raw value this scheme reads from a pixel's first three channels (8-bit values;
    /// gray images pass the same value three times).
    pub fn value(self, r: f64, g: f64, b: f64) -> f64 {
        match self {
            Self::Gray8 | Self::QuantizedU16 | Self::Float32 => r,
            Self::RgbThirds => r + g + b,
            Self::TerrainRgb => r * 65_536.0 + g * 256.0 + b,
            Self::Terrarium => r * 256.0 + g + b / 256.0,
        }
    }

    /// True for the schemes that read three colour channels.
    pub fn needs_rgb(self) -> bool {
        matches!(self, Self::RgbThirds | Self::TerrainRgb | Self::Terrarium)
    }
}

impl ElevationEncoding {
    /// One raw value (see [`ElevationScheme::value`]) -> height in world units.
    pub fn height(&self, v: f64) -> f64 {
        match self.scheme {
            ElevationScheme::Gray8 => self.offset + v / 255.0 * self.scale,
            ElevationScheme::RgbThirds => self.offset + v / 765.0 * self.scale,
            ElevationScheme::TerrainRgb => -10_000.0 + v * 0.1,
            ElevationScheme::Terrarium => v - 32_768.0,
            ElevationScheme::QuantizedU16 => self.offset + v * self.scale,
            ElevationScheme::Float32 => v,
        }
    }

    /// The height difference between two neighbouring raw values: the encoding's
    /// resolution (0 for f32).
    pub fn step(&self) -> f64 {
        match self.scheme {
            ElevationScheme::Gray8 => self.scale / 255.0,
            ElevationScheme::RgbThirds => self.scale / 765.0,
            ElevationScheme::TerrainRgb => 0.1,
            ElevationScheme::Terrarium => 1.0 / 256.0,
            ElevationScheme::QuantizedU16 => self.scale,
            ElevationScheme::Float32 => 0.0,
        }
    }
}

fn one() -> f64 {
    1.0
}

/// One tile set and its grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Layer {
    /// Unique name ("texture", "elevation", ...).
    pub name: String,
    /// What the layer holds.
    pub kind: LayerKind,
    /// Payload encoding of every tile.
    pub format: TileFormat,
    /// Compression around the payload.
    #[serde(default)]
    pub compression: PayloadCompression,
    /// Pixels per tile edge, borders excluded.
    pub tile_resolution: u32,
    /// Pixels duplicated from the neighbours on each side (0..=16).
    #[serde(default)]
    pub border: u8,
    /// Tiles across at LOD 0.
    pub num_x_tiles: u32,
    /// Tiles down at LOD 0.
    pub num_y_tiles: u32,
    /// LODs that may hold tiles (0..num_lods); at most [`Layer::depth`].
    pub num_lods: u8,
    /// World units covered by one LOD-0 tile edge.
    pub tile_world_size: f64,
    /// Height decoding, for elevation layers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevation: Option<ElevationEncoding>,
    /// Where the layer's tiles are: coarsest populated LOD and data bounds (§3.7). Written
    /// by every writer; archives without it get it derived from their directory on open.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub extent: Option<LayerExtent>,
}

impl Layer {
    /// Levels of the layer's quadtree: LOD `depth - 1` is a single tile.
    /// Directory keys are computed with it, whatever `num_lods` is.
    pub fn depth(&self) -> u8 {
        levels_to_one(self.num_x_tiles.max(self.num_y_tiles))
    }

    /// Is `other` the same layer (name, kind, encoding, grid), wherever its data is? Parts
    /// of one terrain (shards, a coarse archive) hold its data in different places.
    pub fn same_grid(&self, other: &Self) -> bool {
        Self { extent: None, ..self.clone() } == Self { extent: None, ..other.clone() }
    }

    /// The coarsest LOD a reader starts the quadtree at: the coarsest populated one where
    /// the layer says (§3.7), else the top of the layer.
    pub fn start_lod(&self) -> u8 {
        let top = self.num_lods.saturating_sub(1);
        self.extent.as_ref().map_or(top, |e| e.coarsest_lod.min(top))
    }

    /// The tiles at `lod` where the layer's data is (the whole grid where it does not say),
    /// as inclusive column and row ranges `(x0, y0, x1, y1)`.
    pub fn data_tiles_at(&self, lod: u8) -> (u32, u32, u32, u32) {
        match &self.extent {
            Some(e) => e.tile_range(self, lod),
            None => {
                let (nx, ny) = self.grid_at(lod);
                (0, 0, nx - 1, ny - 1)
            }
        }
    }

    /// The data's box in world units, `[min x, min z, max x, max z]`: the layer's extent,
    /// else its whole grid.
    pub fn data_world(&self) -> [f64; 4] {
        self.extent.as_ref().map_or_else(
            || {
                let (ex, ez) = self.world_extent();
                [0.0, 0.0, ex, ez]
            },
            |e| e.world,
        )
    }

    /// Where the layer's detail is, `[min x, min z, max x, max z]`: the finest LOD's box
    /// where the layer says (§3.7), else its whole grid.
    pub fn data_detail(&self) -> [f64; 4] {
        self.extent.as_ref().map_or_else(|| self.data_world(), |e| e.detail)
    }

    /// Tiles across and down at `lod`: ceil(n / 2^lod).
    pub fn grid_at(&self, lod: u8) -> (u32, u32) {
        let shrink = |n: u32| {
            if lod >= 32 { 1 } else { n.div_ceil(1 << lod).max(1) }
        };
        (shrink(self.num_x_tiles), shrink(self.num_y_tiles))
    }

    /// World units across one tile at `lod` (`tile_world_size` doubled per LOD).
    pub fn world_size_at(&self, lod: u8) -> f64 {
        self.tile_world_size * f64::from(1u32 << lod.min(31))
    }

    /// World units between two samples at `lod` (a tile's width over its resolution).
    pub fn sample_spacing(&self, lod: u8) -> f64 {
        self.world_size_at(lod) / f64::from(self.tile_resolution)
    }

    /// World units covered by the LOD-0 grid: (x across, z down).
    pub fn world_extent(&self) -> (f64, f64) {
        (f64::from(self.num_x_tiles) * self.tile_world_size, f64::from(self.num_y_tiles) * self.tile_world_size)
    }

    /// Every tile of the grid at `lod`, row by row, as keys of layer `index`.
    pub fn tiles_at(&self, index: u8, lod: u8) -> impl Iterator<Item = TileKey> + use<> {
        let (nx, ny) = self.grid_at(lod);
        (0..ny).flat_map(move |y| (0..nx).filter_map(move |x| TileKey::new(index, lod, x, y).ok()))
    }

    /// Is (lod, x, y) inside this layer's grid?
    pub fn contains(&self, key: TileKey) -> bool {
        let (nx, ny) = self.grid_at(key.lod());
        key.lod() < self.num_lods && key.x() < nx && key.y() < ny
    }

    /// Samples across a stored tile: `tile_resolution + 2 * border`.
    pub fn stored_edge(&self) -> usize {
        self.tile_resolution as usize + 2 * usize::from(self.border)
    }

    /// Largest decoded payload a tile of this layer can have: 16 bytes per sample (raw f32
    /// RGBA at most), the cap for decompressing zstd-stored tiles.
    pub fn max_payload_bytes(&self) -> u64 {
        let px = u64::from(self.tile_resolution) + 2 * u64::from(self.border);
        px * px * 16
    }

    /// Tiles in the full grid at every LOD (an upper bound on the layer's tile count).
    pub fn grid_tiles(&self) -> u64 {
        (0..self.num_lods)
            .map(|lod| {
                let (nx, ny) = self.grid_at(lod);
                u64::from(nx) * u64::from(ny)
            })
            .sum()
    }
}

/// Number of halvings (plus one) that bring `n` tiles down to one.
pub fn levels_to_one(n: u32) -> u8 {
    let mut levels = 1u8;
    let mut side = n.max(1);
    while side > 1 {
        side = side.div_ceil(2);
        levels += 1;
    }
    levels
}

/// Elevation range and runtime mesh parameters (names follow the original engine).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Terrain {
    /// Lowest height in world units.
    pub min_elevation: f64,
    /// Highest height in world units.
    pub max_elevation: f64,
    /// max - min; the span of the 8-bit / RGB-thirds encodings.
    pub displacement: f64,
    /// max - min, kept for the original engine's consumers.
    pub elevation_range: f64,
    /// Original engine's multi-sampling radius against 8-bit stair-steps.
    pub smoothing_range: f64,
    /// Finest mesh grid spacing in world units (= elevation sample spacing).
    pub base_tile_size: f64,
    /// Radius of the finest mesh ring; each next ring doubles it.
    pub high_detail_range: f64,
    /// Number of mesh rings.
    pub num_detail_levels: u32,
    /// Original engine's texture consolidation size.
    pub max_consolidated_texture_resolution: u32,
    /// World extent (x east, z south, from the north-west corner of tile (0, 0)) of the
    /// source's samples; the layers' grids beyond it, rounded up to whole tiles, hold no
    /// data. None: the whole grid (archives made from tile pyramids).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data_extent: Option<[f64; 2]>,
}

impl Terrain {
    /// Lowest and highest height, in order, spanning at least `displacement` (the
    /// encodings' range) above the lowest.
    pub fn height_range(&self) -> (f64, f64) {
        let (lo, hi) = (self.min_elevation.min(self.max_elevation), self.max_elevation.max(self.min_elevation));
        (lo, hi.max(lo + self.displacement.max(0.0)))
    }
}

impl Default for Terrain {
    fn default() -> Self {
        Self {
            min_elevation: 0.0,
            max_elevation: 0.0,
            displacement: 0.0,
            elevation_range: 0.0,
            smoothing_range: 1.0,
            base_tile_size: 1.0,
            high_detail_range: 100.0,
            num_detail_levels: 12,
            max_consolidated_texture_resolution: 1024,
            data_extent: None,
        }
    }
}

/// Where the dataset lies.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Georeference {
    /// Coordinate reference system, e.g. "EPSG:4326".
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crs: Option<String>,
    /// CRS coordinates of the north-west corner of tile (0, 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<[f64; 2]>,
    /// West, south, east, north in degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lat_lon_bounds: Option<[f64; 4]>,
    /// The CRS as a PROJ definition, so that a reader needs no EPSG table to use it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub definition: Option<String>,
    /// CRS units per world unit, along x (east) and y (north). World point `(x, z)` (x east,
    /// z south, from the north-west corner of tile (0, 0)) lies at CRS
    /// `(origin[0] + x * scale[0], origin[1] - z * scale[1])`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<[f64; 2]>,
}

impl Georeference {
    /// The CRS coordinates of world point `(x, z)`, when the origin and scale are known.
    pub fn world_to_crs(&self, x: f64, z: f64) -> Option<(f64, f64)> {
        let (o, s) = (self.origin?, self.scale?);
        Some((o[0] + x * s[0], o[1] - z * s[1]))
    }

    /// The world point at CRS coordinates `(cx, cy)`, when the origin and scale are known.
    pub fn crs_to_world(&self, cx: f64, cy: f64) -> Option<(f64, f64)> {
        let (o, s) = (self.origin?, self.scale?);
        (s[0] != 0.0 && s[1] != 0.0).then(|| ((cx - o[0]) / s[0], (o[1] - cy) / s[1]))
    }
}

/// One field of an original-engine metadata text, as written there.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct OriginalField {
    /// C# type ("int", "float", "double", "string", "bool", ...).
    #[serde(rename = "type")]
    pub ty: String,
    /// Field name.
    pub name: String,
    /// Value literal exactly as written (e.g. `76.963814f`, `"LOD"`).
    pub value: String,
}

impl Metadata {
    /// A document with the given layers and defaults elsewhere.
    pub fn new(name: impl Into<String>, layers: Vec<Layer>) -> Self {
        Self {
            name: name.into(),
            description: String::new(),
            layers,
            terrain: Terrain::default(),
            georeference: None,
            vertical_datum: VerticalDatum::default(),
            original_fields: Vec::new(),
            shard: None,
            sources: Vec::new(),
            extra: serde_json::Map::new(),
        }
    }

    /// Parses and validates a document.
    ///
    /// # Errors
    /// [`Error::Metadata`] on invalid JSON or a layer that breaks the format's limits.
    pub fn from_json(bytes: &[u8]) -> Result<Self> {
        let m: Self = serde_json::from_slice(bytes).map_err(|e| Error::Metadata(e.to_string()))?;
        m.validate()?;
        Ok(m)
    }

    /// Serializes to compact JSON.
    pub fn to_json(&self) -> Vec<u8> {
        // Serializing plain data with string keys cannot fail.
        serde_json::to_vec(self).unwrap_or_default()
    }

    /// Index of the layer called `name`.
    pub fn layer_index(&self, name: &str) -> Option<u8> {
        self.layers.iter().position(|l| l.name == name).and_then(|i| u8::try_from(i).ok())
    }

    /// The layer called `name`, or the layer at index `name` (URLs and the CLI take both).
    pub fn resolve_layer(&self, name: &str) -> Option<u8> {
        self.layer_index(name).or_else(|| name.parse::<u8>().ok().filter(|&i| usize::from(i) < self.layers.len()))
    }

    /// Directory key of a tile, checked against its layer's grid.
    ///
    /// # Errors
    /// [`Error::InvalidTile`] for an unknown layer or a tile outside the layer's grid.
    pub fn directory_key(&self, tile: TileKey) -> Result<u64> {
        let layer = self
            .layers
            .get(usize::from(tile.layer()))
            .ok_or_else(|| Error::InvalidTile { what: format!("{tile}: no such layer") })?;
        if !layer.contains(tile) {
            let (nx, ny) = layer.grid_at(tile.lod());
            return Err(Error::InvalidTile {
                what: format!(
                    "{tile}: outside layer {:?} ({} LODs, {nx}x{ny} tiles at this LOD)",
                    layer.name, layer.num_lods
                ),
            });
        }
        tile.archive_key(layer.depth())
    }

    /// Quadtree depth of every layer, in layer order.
    pub fn depths(&self) -> Vec<u8> {
        self.layers.iter().map(Layer::depth).collect()
    }

    /// The lowest format major version that can hold this metadata: 3 where a layer is a
    /// water layer, 2 where a layer's tiles are `zstd_gradient`, else 1 (FORMAT.md §8).
    pub fn format_major(&self) -> u16 {
        if self.layers.iter().any(|l| l.kind == LayerKind::Water) {
            3
        } else if self.layers.iter().any(|l| l.compression == PayloadCompression::ZstdGradient) {
            2
        } else {
            1
        }
    }

    /// Checks the limits every reader relies on.
    ///
    /// # Errors
    /// [`Error::Metadata`] naming the offending layer and field.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::Metadata(msg));
        if self.layers.is_empty() || self.layers.len() > MAX_LAYERS {
            return bad(format!("{} layers (1..={MAX_LAYERS} allowed)", self.layers.len()));
        }
        for (i, l) in self.layers.iter().enumerate() {
            let at = format!("layer {i} ({:?})", l.name);
            if l.name.is_empty() || l.name.contains(['/', '\\']) || l.name.len() > 64 {
                return bad(format!("{at}: name must be 1..64 characters without slashes"));
            }
            if self.layers[..i].iter().any(|o| o.name == l.name) {
                return bad(format!("{at}: duplicate name"));
            }
            if l.num_x_tiles == 0 || l.num_y_tiles == 0 || l.num_x_tiles > 1 << 28 || l.num_y_tiles > 1 << 28 {
                return bad(format!("{at}: grid {}x{} out of range", l.num_x_tiles, l.num_y_tiles));
            }
            if l.depth() > MAX_LODS || l.num_lods == 0 || l.num_lods > l.depth() {
                return bad(format!("{at}: num_lods {} must be 1..={}", l.num_lods, l.depth()));
            }
            if l.tile_resolution == 0 || l.tile_resolution > 65_536 || l.border > 16 {
                return bad(format!("{at}: tile_resolution {} / border {} out of range", l.tile_resolution, l.border));
            }
            if !(l.tile_world_size.is_finite() && l.tile_world_size > 0.0) {
                return bad(format!("{at}: tile_world_size must be a positive number"));
            }
            if l.compression == PayloadCompression::ZstdGradient && l.format != TileFormat::RawU16 {
                return bad(format!("{at}: compression zstd_gradient is for raw_u16 tiles, not {:?}", l.format));
            }
            if l.kind == LayerKind::Water && l.elevation.is_none() {
                return bad(format!("{at}: a water layer needs an encoding (`elevation`) for its fractions"));
            }
        }
        if let Some(u) = &self.vertical_datum.undulation
            && !u.is_valid()
        {
            return bad("vertical_datum.undulation: a lattice needs positive steps and one value per node".to_owned());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn layer(nx: u32, ny: u32, num_lods: u8) -> Layer {
        Layer {
            name: "texture".into(),
            kind: LayerKind::Texture,
            format: TileFormat::Png,
            compression: PayloadCompression::None,
            tile_resolution: 256,
            border: 0,
            num_x_tiles: nx,
            num_y_tiles: ny,
            num_lods,
            tile_world_size: 76.96,
            elevation: None,
            extent: None,
        }
    }

    #[test]
    fn write_then_read_keeps_unknown_members() {
        let mut m = Metadata::new("t", vec![layer(68, 57, 7)]);
        m.extra.insert("future_field".into(), serde_json::json!({"a": 1}));
        let back = Metadata::from_json(&m.to_json()).unwrap();
        assert_eq!(back, m);
    }

    #[test]
    fn grid_shrinks_by_ceil_half_to_one() {
        let l = layer(68, 57, 8);
        assert_eq!(l.depth(), 8);
        assert_eq!(l.grid_at(0), (68, 57));
        assert_eq!(l.grid_at(1), (34, 29));
        assert_eq!(l.grid_at(3), (9, 8));
        assert_eq!(l.grid_at(7), (1, 1));
        assert_eq!(levels_to_one(1), 1);
        assert_eq!(levels_to_one(2), 2);
        assert_eq!(levels_to_one(3), 3);
    }

    #[test]
    fn rejects_bad_layers() {
        for l in [layer(0, 1, 1), layer(4, 4, 4), layer(4, 4, 0)] {
            assert!(Metadata::new("t", vec![l]).validate().is_err());
        }
        assert!(Metadata::new("t", vec![layer(4, 4, 3), layer(2, 2, 1)]).validate().is_err(), "duplicate names");
        assert!(Metadata::from_json(b"{\"layers\": 5}").is_err());
    }
}
