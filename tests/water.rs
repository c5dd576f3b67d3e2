//! A water layer from a mask raster (`terrastream water`): lakes that the heights' flat-sea
//! rule cannot see, carried in the archive and served as quantized-mesh's water mask.
//! GDAL is the oracle: it makes the mask (rasterized in degrees, warped to UTM with an
//! area average, so the lake's shore holds fractions) and measures the lake's area.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;

use terrastream_format::{LayerKind, Reader, TileKey};
use terrastream_views::quantized::Terrain;
use terrastream_views::quantized::encode::Extensions;
use terrastream_views::quantized::geodetic::GeoTile;

#[path = "support/oracles.rs"]
mod oracles;
use oracles::terrastream;

/// The lake's radius in degrees ([`oracles::lake_mask`]).
const RADIUS: f64 = oracles::LAKE_RADIUS;

/// The coast DEM and a mask of a lake in its basin ([`oracles::lake_mask`]); the basin's
/// centre (lon, lat).
fn coast_and_lake(dir: &Path) -> (PathBuf, PathBuf, (f64, f64)) {
    let (dem, bounds) = oracles::coast_dem(dir);
    let (mask, centre) = oracles::lake_mask(dir, bounds);
    (dem, mask, centre)
}

/// GDAL's `gdal_translate` with `options` from `files[0]` to `files[1]`.
fn gdal_translate(options: &[&str], files: [&str; 2]) {
    let out = Command::new("gdal_translate").arg("-q").args(options).args(files).output().unwrap();
    assert!(out.status.success(), "gdal_translate: {}", String::from_utf8_lossy(&out.stderr));
}

/// `terrastream water archive --mask mask`, which must fail: what it said.
fn refused(archive: &Path, mask: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(["water", archive.to_str().unwrap(), "--mask", mask.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!out.status.success(), "refused: {}", mask.display());
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The lake's area in square metres by GDAL: the mask's mean (no data left out) times its
/// valid pixels times a pixel's area.
fn gdal_lake_area(mask: &Path) -> f64 {
    let out = Command::new("gdalinfo").args(["-json", "-stats", mask.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "gdalinfo: {}", String::from_utf8_lossy(&out.stderr));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let band = &info["bands"][0];
    let mean: f64 = band["metadata"][""]["STATISTICS_MEAN"].as_str().unwrap().parse().unwrap();
    let valid: f64 = band["metadata"][""]["STATISTICS_VALID_PERCENT"].as_str().unwrap().parse().unwrap();
    let size = info["size"].as_array().unwrap();
    let pixels = size[0].as_f64().unwrap() * size[1].as_f64().unwrap() * valid / 100.0;
    mean * pixels * 400.0
}

/// The water layer's index and its LOD-0 tiles decoded: the fraction of water at each
/// sample (NaN where the mask said nothing).
fn water_tiles(reader: &Reader<terrastream_format::MmapSource>) -> (usize, Vec<(TileKey, Vec<f32>)>) {
    let metadata = reader.metadata();
    let index = metadata.layers.iter().position(|l| l.kind == LayerKind::Water).expect("a water layer");
    let layer = &metadata.layers[index];
    let mut tiles = vec![];
    reader
        .for_each_tile(|key, stored| -> Result<(), terrastream_format::Error> {
            if usize::from(key.layer()) == index && key.lod() == 0 {
                let decoded = terrastream_tiles::decode(layer, key, stored, true).unwrap();
                let terrastream_tiles::TileData::Heights { heights, .. } = decoded.data else { panic!("{key}") };
                tiles.push((key, heights));
            }
            Ok(())
        })
        .unwrap();
    (index, tiles)
}

/// The quantized-mesh water mask of `tile` (only that extension asked): one byte, or
/// 256 x 256 rows from the north. The extension is the tile's last bytes: its id (2), its
/// length, its data.
fn served_mask(reader: &Reader<terrastream_format::MmapSource>, tile: GeoTile) -> Vec<u8> {
    let terrain = Terrain::new(reader, None).unwrap();
    let only_water = Extensions { normals: false, water: true, metadata: false };
    let bytes = terrain.tile(tile, only_water).unwrap().expect("the tile exists");
    for len in [65_536usize, 1] {
        let Some(at) = bytes.len().checked_sub(len + 5) else { continue };
        if bytes[at] == 2 && u32::from_le_bytes(bytes[at + 1..at + 5].try_into().unwrap()) as usize == len {
            return bytes[at + 5..].to_vec();
        }
    }
    panic!("no water mask at the end of tile {tile:?}");
}

/// The water mask of `tile` as PyPI `quantized-mesh-tile` decodes it (installed by
/// `scripts/test.sh` in the tools' virtual environment) equals `ours`.
fn independent_decoder_agrees(reader: &Reader<terrastream_format::MmapSource>, tile: GeoTile, ours: &[u8], dir: &Path) {
    let venv = std::env::var_os("TERRASTREAM_TOOLS_VENV").map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/terrastream-tools")
    });
    let python = venv.join("bin/python");
    let has = Command::new(&python).args(["-c", "import quantized_mesh_tile"]).status().is_ok_and(|s| s.success());
    if !has {
        assert!(
            std::env::var_os("CI").is_none(),
            "quantized-mesh-tile is required on CI (scripts/test.sh installs it)"
        );
        eprintln!("\n*** SKIPPING the independent decoder: PyPI quantized-mesh-tile is not installed ***\n");
        return;
    }
    let only_water = Extensions { normals: false, water: true, metadata: false };
    let bytes = Terrain::new(reader, None).unwrap().tile(tile, only_water).unwrap().unwrap();
    let path = dir.join("lake.terrain");
    std::fs::write(&path, bytes).unwrap();
    let script = "import io, json, sys\n\
from quantized_mesh_tile.terrain import TerrainTile\n\
t = TerrainTile()\n\
t.fromBytesIO(io.BytesIO(open(sys.argv[1], 'rb').read()), hasWatermask=True)\n\
print(json.dumps([v for row in t.watermask for v in row]))\n";
    let out = Command::new(&python).args(["-c", script, path.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "the decoder: {}", String::from_utf8_lossy(&out.stderr));
    let theirs: Vec<u8> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(theirs.len(), ours.len(), "the mask's length");
    assert!(theirs == ours, "quantized-mesh-tile decodes another water mask");
}

/// The mask in UTM is carried into the archive's water layer (the archive in its own
/// transverse Mercator): the lake's area as GDAL measures it within 3 %, no data over
/// the sea, every other tile stored as before, format major 3; added again, it replaces
/// the layer; `tile --water` makes the same archive; and the quantized-mesh mask (as PyPI
/// `quantized-mesh-tile` decodes it too) shows the lake where the heights alone show land,
/// while the sea stays water by the flat-0 rule.
#[test]
fn a_lake_from_a_mask_in_another_crs_is_water() {
    let dir = tempfile::tempdir().unwrap();
    let (dem, mask, centre) = coast_and_lake(dir.path());
    let plain = dir.path().join("coast.tspack");
    let wet = dir.path().join("coast-water.tspack");
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", plain.to_str().unwrap()]);
    terrastream(&["water", plain.to_str().unwrap(), "--mask", mask.to_str().unwrap(), "-o", wet.to_str().unwrap()]);

    let reader = Reader::open_mmap(&wet).unwrap();
    assert_eq!(reader.header().version_major, 3);
    let (index, tiles) = water_tiles(&reader);
    assert!(!tiles.is_empty());
    let elevation = reader.metadata().layers.iter().position(|l| l.kind == LayerKind::Elevation).unwrap();
    let layer = &reader.metadata().layers[elevation];
    let (res, border) = (layer.tile_resolution as usize, usize::from(layer.border));
    let spacing = layer.sample_spacing(0);
    let edge = res + 2 * border;
    // The interior samples: the lake's area, and the share the mask says nothing of.
    let (mut area, mut unknown, mut samples) = (0.0, 0usize, 0usize);
    for (_, values) in &tiles {
        for row in border..border + res {
            for &v in &values[row * edge + border..row * edge + border + res] {
                samples += 1;
                if v.is_nan() {
                    unknown += 1;
                } else {
                    assert!((0.0..=1.0).contains(&v), "a fraction: {v}");
                    area += f64::from(v) * spacing * spacing;
                }
            }
        }
    }
    let truth = gdal_lake_area(&mask);
    eprintln!(
        "lake area: ours {area:.0} m², GDAL's {truth:.0} m² ({:.4}x); {unknown} of {samples} samples unknown",
        area / truth
    );
    assert!((area / truth - 1.0).abs() < 0.03, "ours {area:.0} m², GDAL's {truth:.0} m²");
    assert!(unknown > 0, "the sea's half has no mask: no data there");

    // Every tile of the other layers is stored as it was.
    let before = terrastream_testkit::archives::stored_tiles(&plain);
    let after = terrastream_testkit::archives::stored_tiles(&wet);
    let others: std::collections::BTreeMap<_, _> =
        after.iter().filter(|(k, _)| usize::from(k.layer()) != index).map(|(k, v)| (*k, v.clone())).collect();
    assert_eq!(others, before, "the archive's own tiles");

    // Added again over itself: one water layer, the same tiles.
    terrastream(&["water", wet.to_str().unwrap(), "--mask", mask.to_str().unwrap()]);
    let again = terrastream_testkit::archives::stored_tiles(&wet);
    assert_eq!(again, after);
    // A mask 2048 pixels wider on every side (no data there, its pixels on the same
    // lattice): the same tiles, reading only its rows and columns under the archive.
    let padded = dir.path().join("padded.tif");
    gdal_translate(&["-srcwin", "-2048", "-2048", "5000", "5000"], [mask.to_str().unwrap(), padded.to_str().unwrap()]);
    let from_padded = dir.path().join("padded.tspack");
    terrastream(&[
        "water",
        plain.to_str().unwrap(),
        "--mask",
        padded.to_str().unwrap(),
        "-o",
        from_padded.to_str().unwrap(),
    ]);
    assert_eq!(terrastream_testkit::archives::stored_tiles(&from_padded), after, "the padded mask");
    // In place, on an archive written with room for updates (FORMAT.md §7.1): the water
    // tiles appended and its own tiles' bytes left where they were, the same tiles as a
    // copy written anew.
    let roomy = dir.path().join("roomy.tspack");
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "--tile-size", "64", "-o", roomy.to_str().unwrap()]);
    let (in_place, anew) = (dir.path().join("in-place.tspack"), dir.path().join("anew.tspack"));
    std::fs::copy(&roomy, &in_place).unwrap();
    terrastream(&["water", in_place.to_str().unwrap(), "--mask", mask.to_str().unwrap()]);
    terrastream(&["water", roomy.to_str().unwrap(), "--mask", mask.to_str().unwrap(), "-o", anew.to_str().unwrap()]);
    let stored = terrastream_testkit::archives::stored_tiles;
    assert_eq!(stored(&in_place), stored(&anew), "in place and anew");
    let data = Reader::open_mmap(&roomy).unwrap().header().data;
    let span = data.offset as usize..(data.offset + data.len) as usize;
    let (old_bytes, new_bytes) = (std::fs::read(&roomy).unwrap(), std::fs::read(&in_place).unwrap());
    assert_eq!(new_bytes[span.clone()], old_bytes[span], "the archive's tiles where they were");
    assert_eq!(Reader::open_mmap(&in_place).unwrap().header().version_major, 3);
    // `tile --water` makes the same archive in one run.
    let one_run = dir.path().join("one-run.tspack");
    let (dem, mask) = (dem.to_str().unwrap(), mask.to_str().unwrap());
    terrastream(&["tile", "--elevation", dem, "--water", mask, "-o", one_run.to_str().unwrap()]);
    assert_eq!(terrastream_testkit::archives::stored_tiles(&one_run), after, "tile --water");

    // An update of the heights over part of the land keeps the water tiles as they are.
    let updated = dir.path().join("updated.tspack");
    std::fs::copy(&wet, &updated).unwrap();
    let raised = dir.path().join("raised.tif");
    gdal_translate(
        &["-ot", "Float32", "-srcwin", "150", "60", "60", "60", "-scale", "0", "1000", "5", "1005"],
        [dem, raised.to_str().unwrap()],
    );
    terrastream(&["update", updated.to_str().unwrap(), "--elevation", raised.to_str().unwrap(), "--in-place"]);
    let water_of = |tiles: &std::collections::BTreeMap<TileKey, Vec<u8>>| {
        tiles.iter().filter(|(k, _)| usize::from(k.layer()) == index).map(|(k, v)| (*k, v.clone())).collect::<Vec<_>>()
    };
    let after_update = terrastream_testkit::archives::stored_tiles(&updated);
    assert_ne!(after_update, after, "the update changed heights");
    assert_eq!(water_of(&after_update), water_of(&after), "the water tiles after an update");

    // The quantized-mesh mask at the deepest level: the tile holding the lake's centre.
    let plain_reader = Reader::open_mmap(&plain).unwrap();
    let z = Terrain::new(&reader, None).unwrap().maxzoom();
    let d = 180.0 / f64::from(1u32 << z);
    let (x, y) = (((centre.0 + 180.0) / d).floor() as u32, ((centre.1 + 90.0) / d).floor() as u32);
    let tile = GeoTile::new(z, x, y).unwrap();
    // The centre's pixel in the mask (rows from the north).
    let (u, v) = (
        ((centre.0 + 180.0 - f64::from(x) * d) / d * 256.0) as usize,
        ((f64::from(y + 1) * d - (centre.1 + 90.0)) / d * 256.0) as usize,
    );
    let lake = served_mask(&reader, tile);
    let without = served_mask(&plain_reader, tile);
    independent_decoder_agrees(&reader, tile, &lake, dir.path());
    let at = |m: &[u8], u: usize, v: usize| if m.len() == 1 { m[0] } else { m[v.min(255) * 256 + u.min(255)] };
    eprintln!(
        "tile {tile:?}: the lake's centre at ({u}, {v}): {} with the layer, {} without",
        at(&lake, u, v),
        at(&without, u, v)
    );
    assert_eq!(at(&without, u, v), 0, "the heights alone: the basin is land");
    assert_eq!(at(&lake, u, v), 255, "the layer: the lake");
    // A point on the shore's far side, 1.5 radii east of the centre, is land.
    let pixels_east = (1.5 * RADIUS / d * 256.0) as usize;
    if u + pixels_east < 256 {
        assert_eq!(at(&lake, u + pixels_east, v), 0, "east of the lake");
    }
    // The sea (the DEM's west quarter, where the mask has no data): the flat 0.
    let sea = GeoTile::new(z, ((-20.025 + 180.0) / d).floor() as u32, y).unwrap();
    assert_eq!(served_mask(&reader, sea), vec![255], "the sea by the heights' rule");
}

/// A mask that does not say where it lies, or lies elsewhere, is refused, naming it, and
/// the archive is left as it was.
#[test]
fn a_mask_without_a_georeference_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let (dem, _, _) = coast_and_lake(dir.path());
    let archive = dir.path().join("coast.tspack");
    terrastream(&["tile", "--elevation", dem.to_str().unwrap(), "-o", archive.to_str().unwrap()]);
    let bare = dir.path().join("bare.tif");
    gdal_translate(
        &["-of", "GTiff", "-co", "PROFILE=BASELINE", "-outsize", "64", "64"],
        [dem.to_str().unwrap(), bare.to_str().unwrap()],
    );
    // GDAL keeps the georeference of a baseline TIFF beside it, where it is read too.
    let _ = std::fs::remove_file(dir.path().join("bare.tif.aux.xml"));
    let before = std::fs::read(&archive).unwrap();
    let stderr = refused(&archive, &bare);
    assert!(stderr.contains("bare.tif") && stderr.contains("georeference"), "{stderr}");
    assert_eq!(std::fs::read(&archive).unwrap(), before, "the archive as it was");

    // A mask that lies elsewhere (the same pixels placed in Europe) is refused too.
    let elsewhere = dir.path().join("elsewhere.tif");
    gdal_translate(
        &["-a_srs", "EPSG:4326", "-a_ullr", "10", "50", "11", "49"],
        [dem.to_str().unwrap(), elsewhere.to_str().unwrap()],
    );
    let stderr = refused(&archive, &elsewhere);
    assert!(stderr.contains("elsewhere.tif") && stderr.contains("says nothing"), "{stderr}");
    assert_eq!(std::fs::read(&archive).unwrap(), before, "the archive as it was");
}

/// `terrastream` with `args`, which must succeed: what it wrote to stderr (its warnings).
fn warnings(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(args).output().unwrap();
    assert!(out.status.success(), "terrastream {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A sharded run with water: each shard holds the water tiles of its own elevation tiles
/// (`tile --shard --water`), and the merge makes those above the split from the mask
/// (`merge --water`): the single run's archive tile for tile, and published as a
/// manifest, every water tile where it routes it. Without the mask the merge says what
/// is missing; a shard beyond the mask holds the layer without tiles; a manifest's mask
/// over shards without water is refused.
#[test]
fn shards_hold_their_water_and_the_merge_makes_the_rest_from_the_mask() {
    let dir = tempfile::tempdir().unwrap();
    let (dem, mask, _) = coast_and_lake(dir.path());
    let (dem, mask) = (dem.to_str().unwrap(), mask.to_str().unwrap());
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_owned();
    let tiled = ["tile", "--elevation", dem, "--tile-size", "32"];
    terrastream(&[&tiled[..], &["--water", mask, "-o", &path("whole.tspack")]].concat());
    let whole = terrastream_testkit::archives::stored_tiles(Path::new(&path("whole.tspack")));
    let water = Reader::open_mmap(path("whole.tspack"))
        .unwrap()
        .metadata()
        .layers
        .iter()
        .position(|l| l.kind == LayerKind::Water)
        .unwrap();
    let wet = |tiles: &std::collections::BTreeMap<TileKey, Vec<u8>>| {
        tiles.keys().filter(|k| usize::from(k.layer()) == water).count()
    };
    let shards: Vec<String> = (0..3).map(|i| path(&format!("s{i}.tspack"))).collect();
    for (i, shard) in shards.iter().enumerate() {
        let plain = path(&format!("plain{i}.tspack"));
        terrastream(&[&tiled[..], &["--shard", &format!("{i}/3"), "-o", &plain]].concat());
        terrastream(&[&tiled[..], &["--shard", &format!("{i}/3"), "--water", mask, "-o", shard]].concat());
        // `water` of a shard written without it: the same shard.
        terrastream(&["water", &plain, "--mask", mask]);
        let stored = |p: &str| terrastream_testkit::archives::stored_tiles(Path::new(p));
        assert_eq!(stored(&plain), stored(shard), "shard {i}: water added afterwards");
        // Its water tiles are the single run's, one for each of its elevation tiles.
        let own = stored(shard);
        let split = Reader::open_mmap(shard).unwrap().metadata().shard.clone().unwrap().split_lods[water];
        for (key, bytes) in own.iter().filter(|(k, _)| usize::from(k.layer()) == water) {
            assert!(key.lod() <= split, "shard {i}: water tile {key:?} above its split LOD {split}");
            assert_eq!(Some(bytes), whole.get(key), "shard {i}: water tile {key:?}");
        }
        assert!(wet(&own) > 0, "shard {i} holds water tiles");
    }

    // Merged without the mask: the levels above the split have no water, and it says so.
    let refs: Vec<&str> = shards.iter().map(String::as_str).collect();
    let said = warnings(&[&["merge"], &refs[..], &["-o", &path("bare.tspack")]].concat());
    assert!(said.contains("--water MASK") && said.contains("LOD"), "{said}");
    let bare = terrastream_testkit::archives::stored_tiles(Path::new(&path("bare.tspack")));
    assert!(wet(&bare) < wet(&whole), "no water above the split: {} of {}", wet(&bare), wet(&whole));
    // With it: the single run's tiles, every layer.
    let said = warnings(&[&["merge"], &refs[..], &["-o", &path("merged.tspack"), "--water", mask]].concat());
    assert!(!said.contains("--water MASK"), "{said}");
    assert_eq!(terrastream_testkit::archives::stored_tiles(Path::new(&path("merged.tspack"))), whole);

    // Published as they are: the coarse archive holds the water above the split, and the
    // manifest routes every water tile to the archive that holds it.
    let manifest = path("terrain.json");
    terrastream(
        &[&["merge"], &refs[..], &["-o", &path("coarse.tspack"), "--manifest", &manifest, "--water", mask]].concat(),
    );
    let verified = Command::new(env!("CARGO_BIN_EXE_terrastream")).args(["verify", &manifest]).output().unwrap();
    assert!(verified.status.success(), "verify: {}", String::from_utf8_lossy(&verified.stdout));
    let coarse = terrastream_testkit::archives::stored_tiles(Path::new(&path("coarse.tspack")));
    let mut published: std::collections::BTreeMap<TileKey, Vec<u8>> = coarse.clone();
    for shard in &shards {
        published.extend(terrastream_testkit::archives::stored_tiles(Path::new(shard)));
    }
    assert_eq!(published, whole, "the coarse archive and the shards hold the single run's tiles");
    assert!(wet(&coarse) > 0, "the coarse archive's water");

    // A shard whose band the mask does not reach (a mask of the northernmost rows only, the
    // last shard the southernmost): it holds the layer without tiles, as its siblings do;
    // the whole archive's water from that mask would hold some.
    let info = Command::new("gdalinfo").args(["-json", mask]).output().unwrap();
    let info: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
    let (width, height) = (info["size"][0].as_u64().unwrap(), info["size"][1].as_u64().unwrap());
    let north = path("north.tif");
    gdal_translate(&["-srcwin", "0", "0", &width.to_string(), &(height / 10).to_string()], [mask, north.as_str()]);
    let south = path("south.tspack");
    terrastream(&[&tiled[..], &["--shard", "2/3", "--water", &north, "-o", &south]].concat());
    let reader = Reader::open_mmap(&south).unwrap();
    assert!(reader.metadata().layers.iter().any(|l| l.kind == LayerKind::Water), "the layer");
    let south_tiles = terrastream_testkit::archives::stored_tiles(Path::new(&south));
    assert_eq!(wet(&south_tiles), 0, "no water tiles beyond the mask");
    assert!(!south_tiles.is_empty(), "the shard's own tiles");
    let north_archive = path("north.tspack");
    terrastream(&[&tiled[..], &["--water", &north, "-o", &north_archive]].concat());
    assert!(wet(&terrastream_testkit::archives::stored_tiles(Path::new(&north_archive))) > 0, "the mask's rows");

    // A mask for the manifest of shards without water: refused, naming the first shard.
    let plains: Vec<String> = (0..3).map(|i| path(&format!("bare{i}.tspack"))).collect();
    for (i, plain) in plains.iter().enumerate() {
        terrastream(&[&tiled[..], &["--shard", &format!("{i}/3"), "-o", plain]].concat());
    }
    let refs: Vec<&str> = plains.iter().map(String::as_str).collect();
    let out = Command::new(env!("CARGO_BIN_EXE_terrastream"))
        .args(
            [&["merge"], &refs[..], &["-o", &path("c2.tspack"), "--manifest", &path("m2.json"), "--water", mask]]
                .concat(),
        )
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("bare0.tspack") && stderr.contains("no water layer"), "{stderr}");
    assert!(!dir.path().join("m2.json").exists(), "no manifest written");
}
