//! pack -> extract gives back the input files byte for byte; bad input is named.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use std::path::Path;

use common::tree;
use terrastream_format::{LayerKind, MmapSource, Reader, TileKey, verify};
use terrastream_pack::extract::{Layout, extract};
use terrastream_pack::import::{OriginalLayout, Scheme, XyzOptions, pack, scan_original, scan_xyz};
use terrastream_pack::progress::{Progress, Silent};
use terrastream_pack::sample::write_sample_pyramid;
use terrastream_pack::{Error, WriterOptions};

fn pack_dir(input: &Path, out: &Path) -> Reader<MmapSource> {
    let scanned = scan_original(input, &OriginalLayout::default()).unwrap();
    pack(scanned, out, WriterOptions::default(), &Silent::default()).unwrap();
    Reader::new(MmapSource::open(out).unwrap()).unwrap()
}

#[test]
fn original_layout_round_trips_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("sample");
    write_sample_pyramid(&input).unwrap();
    let reader = pack_dir(&input, &dir.path().join("s.tspack"));
    let meta = reader.metadata();
    assert_eq!(meta.layers.len(), 2);
    assert_eq!((meta.layers[0].num_x_tiles, meta.layers[0].num_y_tiles, meta.layers[0].num_lods), (8, 6, 4));
    assert_eq!(meta.layers[1].kind, LayerKind::Elevation);
    assert_eq!(meta.terrain.displacement, 500.0);
    assert!(meta.original_fields.iter().any(|f| f.name == "sampleName"), "unknown fields are kept");
    // The lake tile is missing at LOD 0 and falls back to its parent.
    let lake = TileKey::new(0, 0, 1, 4).unwrap();
    assert!(reader.tile(lake).unwrap().is_none());
    assert_eq!(reader.tile_or_coarser(lake).unwrap().unwrap().0, TileKey::new(0, 1, 0, 2).unwrap());

    let out = dir.path().join("extracted");
    let summary = extract(&reader, &out, Layout::Original, &Silent::default()).unwrap();
    assert_eq!(summary.files, reader.header().addressed_tiles);
    assert_eq!(tree(&input), tree(&out), "extract must reproduce the input tree exactly");
}

#[test]
fn sub_folders_and_custom_names_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in");
    // Max-files-per-folder split and a name with text around x and y; y given first.
    for (lod, n) in [(0u32, 4u32), (1, 2), (2, 1)] {
        for y in 0..n {
            for x in 0..n {
                let sub = input.join(format!("LOD{lod}/part{}", (y * n + x) / 5));
                std::fs::create_dir_all(&sub).unwrap();
                // JPEG start + a start-of-frame for 256x256, then bytes naming the tile.
                let mut jpg = vec![0xff, 0xd8, 0xff, 0xc0, 0, 11, 8, 1, 0, 1, 0, 1, 1, 0x11, 0];
                jpg.extend([lod as u8, x as u8, y as u8]);
                std::fs::write(sub.join(format!("tile_r{y}_c{x}.jpg")), jpg).unwrap();
            }
        }
    }
    let scanned = scan_original(&input, &OriginalLayout { kind: LayerKind::Texture, swap_xy: true }).unwrap();
    assert_eq!(scanned.tiles.len(), 16 + 4 + 1);
    let out = dir.path().join("x.tspack");
    pack(scanned, &out, WriterOptions::default(), &Silent::default()).unwrap();
    let reader = Reader::new(MmapSource::open(&out).unwrap()).unwrap();
    assert_eq!(reader.metadata().layers[0].tile_resolution, 256);
    assert_eq!(&reader.tile(TileKey::new(0, 0, 3, 1).unwrap()).unwrap().unwrap()[15..], &[0, 3, 1]);
    let back = dir.path().join("back");
    extract(&reader, &back, Layout::Original, &Silent::default()).unwrap();
    assert_eq!(&std::fs::read(back.join("LOD0/tile_r1_c3.jpg")).unwrap()[15..], [0, 3, 1]);
}

fn write_xyz(root: &Path, max_zoom: u32, tms: bool) {
    for z in 0..=max_zoom {
        let n = 1u32 << z;
        for x in 0..n {
            for y in 0..n {
                if z == max_zoom && (x + y) % 4 == 1 {
                    continue; // sparse finest zoom
                }
                let folder = root.join(format!("{z}/{x}"));
                std::fs::create_dir_all(&folder).unwrap();
                let mut png = b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\x01\0\0\0\x01\0".to_vec();
                png.extend(format!("{z}/{x}/{y}/{tms}").bytes());
                std::fs::write(folder.join(format!("{y}.png")), png).unwrap();
            }
        }
    }
}

#[test]
fn xyz_and_tms_trees_round_trip_and_map_zoom_to_lod() {
    for tms in [false, true] {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("xyz");
        write_xyz(&input, 3, tms);
        let options = XyzOptions {
            template: "{z}/{x}/{y}.png".into(),
            scheme: if tms { Scheme::Tms } else { Scheme::Xyz },
            kind: LayerKind::Texture,
            elevation: None,
        };
        let scanned = scan_xyz(&input, &options).unwrap();
        let out = dir.path().join("x.tspack");
        pack(scanned, &out, WriterOptions::default(), &Silent::default()).unwrap();
        let reader = Reader::new(MmapSource::open(&out).unwrap()).unwrap();
        let layer = &reader.metadata().layers[0];
        assert_eq!((layer.num_lods, layer.num_x_tiles, layer.tile_resolution), (4, 8, 256));
        // z = 0 is LOD 3; TMS rows are flipped to our north-up rows.
        let top = reader.tile(TileKey::new(0, 3, 0, 0).unwrap()).unwrap().unwrap();
        assert!(top.ends_with(format!("0/0/0/{tms}").as_bytes()));
        let z1 = reader.tile(TileKey::new(0, 2, 0, 0).unwrap()).unwrap().unwrap();
        let want_y = if tms { 1 } else { 0 };
        assert!(z1.ends_with(format!("1/0/{want_y}/{tms}").as_bytes()));
        let back = dir.path().join("back");
        extract(&reader, &back, Layout::Xyz, &Silent::default()).unwrap();
        assert_eq!(tree(&input), tree(&back));
    }
}

#[test]
fn bad_input_names_the_file_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("sample");
    write_sample_pyramid(&input).unwrap();
    let out = dir.path().join("out.tspack");

    // Not an image.
    std::fs::write(input.join("textures/LOD1/3_0.png"), b"hello").unwrap();
    let scanned = scan_original(&input, &OriginalLayout::default()).unwrap();
    let err = pack(scanned, &out, WriterOptions::default(), &Silent::default()).unwrap_err();
    assert!(matches!(&err, Error::Input { path, .. } if path.ends_with("textures/LOD1/3_0.png")), "{err}");
    assert!(!out.exists());

    // A JPEG among PNGs.
    std::fs::write(input.join("textures/LOD1/3_0.png"), [0xff, 0xd8, 0xff, 0xdb]).unwrap();
    let scanned = scan_original(&input, &OriginalLayout::default()).unwrap();
    let err = pack(scanned, &out, WriterOptions::default(), &Silent::default()).unwrap_err();
    assert!(err.to_string().contains("3_0.png") && err.to_string().contains("Jpeg"), "{err}");
    assert!(!out.exists());
    std::fs::remove_file(input.join("textures/LOD1/3_0.png")).unwrap();

    // A tile outside the grid the metadata declares.
    std::fs::copy(input.join("textures/LOD0/0_0.png"), input.join("textures/LOD0/8_0.png")).unwrap();
    let err = scan_original(&input, &OriginalLayout::default()).unwrap_err();
    assert!(err.to_string().contains("8_0.png") && err.to_string().contains("outside"), "{err}");
    std::fs::remove_file(input.join("textures/LOD0/8_0.png")).unwrap();

    // A malformed metadata line, reported with its number.
    let meta = input.join("metadata.txt");
    let mut text = std::fs::read_to_string(&meta).unwrap();
    text = text.replacen("public int TEXTURES_numTextureLODS = 4;", "public int TEXTURES_numTextureLODS 4;", 1);
    std::fs::write(&meta, text).unwrap();
    let err = scan_original(&input, &OriginalLayout::default()).unwrap_err();
    assert!(matches!(err, Error::OriginalMetadata { line: 2, .. }), "{err}");
    assert!(err.to_string().contains("metadata.txt:2:"), "{err}");

    // An empty folder.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    assert!(scan_original(&empty, &OriginalLayout::default()).unwrap_err().to_string().contains("empty"));
    assert_eq!(
        std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "tspack"))
            .count(),
        0
    );
}

/// Stops after `after` tiles, like a Ctrl-C in the middle of a pack.
struct StopAfter {
    after: u64,
    done: std::sync::atomic::AtomicU64,
}

impl Progress for StopAfter {
    fn start(&self, _: &str, _: u64) {}
    fn advance(&self, n: u64) {
        self.done.fetch_add(n, std::sync::atomic::Ordering::SeqCst);
    }
    fn cancelled(&self) -> bool {
        self.done.load(std::sync::atomic::Ordering::SeqCst) >= self.after
    }
}

#[test]
fn an_interrupted_pack_leaves_no_file_behind() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("xyz");
    write_xyz(&input, 5, false); // > 256 tiles: more than one read chunk
    let out_dir = dir.path().join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let out = out_dir.join("x.tspack");
    let options = XyzOptions {
        template: "{z}/{x}/{y}.png".into(),
        scheme: Scheme::Xyz,
        kind: LayerKind::Texture,
        elevation: None,
    };
    let scanned = scan_xyz(&input, &options).unwrap();
    let stop = StopAfter { after: 256, done: 0.into() };
    let err = pack(scanned, &out, WriterOptions::default(), &stop).unwrap_err();
    assert!(matches!(err, Error::Interrupted(_)));
    assert_eq!(std::fs::read_dir(&out_dir).unwrap().count(), 0, "no archive and no temporary file left");

    // Replacing an existing archive: the old one stays intact until the new one is complete.
    let scanned = scan_xyz(&input, &options).unwrap();
    pack(scanned, &out, WriterOptions::default(), &Silent::default()).unwrap();
    let before = std::fs::read(&out).unwrap();
    let scanned = scan_xyz(&input, &options).unwrap();
    assert!(pack(scanned, &out, WriterOptions::default(), &StopAfter { after: 1, done: 0.into() }).is_err());
    assert_eq!(std::fs::read(&out).unwrap(), before);
    assert!(verify(&Reader::new(MmapSource::open(&out).unwrap()).unwrap(), |_| {}).unwrap().is_ok());
}
