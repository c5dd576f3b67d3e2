//! Damaged and hostile archives: every error is clear, nothing panics, nothing is missed.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::cast_possible_truncation, missing_docs)]

mod common;

use std::io::Write;

use common::{layer, metadata};
use terrastream_format::{
    Compression, Directory, Entry, Error, FileSource, HEADER_LEN, Header, LeafPointer, MemorySource, MmapSource,
    Reader, Section, TileKey, crc32c, verify,
};
use terrastream_pack::zstd_compress;
use terrastream_testkit::archives::tiny_archive;

/// Opens and fully verifies; Ok(()) only if the archive is sound.
fn open_and_verify(bytes: Vec<u8>) -> Result<(), String> {
    let reader = Reader::new(MemorySource::new(bytes)).map_err(|e| e.to_string())?;
    let report = verify(&reader, |_| {}).map_err(|e| e.to_string())?;
    if report.is_ok() { Ok(()) } else { Err(report.problems.join("; ")) }
}

/// A small archive with leaf directories, runs and duplicates: every section present.
fn small_archive_with_leaves() -> Vec<u8> {
    let meta = metadata(vec![layer("texture", 40, 30, 4), layer("elevation", 2, 2, 2)]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.tspack");
    let mut tiles = Vec::new();
    for (li, l) in meta.layers.iter().enumerate() {
        for lod in 0..l.num_lods {
            let (nx, ny) = l.grid_at(lod);
            for y in 0..ny {
                for x in 0..nx {
                    let t = TileKey::new(li as u8, lod, x, y).unwrap();
                    let payload = if (x + y) % 3 == 0 { b"dup".to_vec() } else { format!("{t}").into_bytes() };
                    tiles.push((terrastream_pack::Writer::order_key(&meta, t).unwrap(), t, payload));
                }
            }
        }
    }
    tiles.sort_by_key(|t| t.0);
    let options = terrastream_pack::WriterOptions { leaf_entries: 4, bootstrap_target: 1200, ..Default::default() };
    let mut w = terrastream_pack::Writer::create(&path, meta, options).unwrap();
    for (_, t, p) in tiles {
        w.add(t, p).unwrap();
    }
    assert!(w.finish().unwrap().leaf_count > 1);
    std::fs::read(&path).unwrap()
}

/// The offsets of every byte of the header and the sections it names.
fn in_sections(header: &Header) -> impl Iterator<Item = usize> {
    let sections = [header.metadata, header.root_dir, header.leaf_dirs, header.data];
    let ranges = sections.map(|s| usize::try_from(s.offset).unwrap()..usize::try_from(s.end().unwrap()).unwrap());
    (0..HEADER_LEN).chain(ranges.into_iter().flatten())
}

#[test]
fn every_single_byte_flip_is_detected() {
    let good = small_archive_with_leaves();
    assert_eq!(open_and_verify(good.clone()), Ok(()));
    // Every byte of every section is covered by a checksum: header, metadata, root, each
    // leaf (in the root), each tile (its trailer). So every flip there must be caught.
    // (The room left between sections for updates is no section: nothing reads it.)
    let header = Header::decode(&good, good.len() as u64).unwrap();
    let data_start = usize::try_from(header.data.offset).unwrap();
    let mut undetected = Vec::new();
    // Every byte of header, metadata and directories; every 31st byte of the tile data (each blob has its own CRC).
    for i in in_sections(&header).filter(|&i| i < data_start).chain((data_start..good.len()).step_by(31)) {
        let mut bad = good.clone();
        bad[i] ^= 0x5a;
        if open_and_verify(bad).is_ok() {
            undetected.push(i);
        }
    }
    assert!(undetected.is_empty(), "flips at {:?} went unnoticed", &undetected[..undetected.len().min(10)]);
}

#[test]
fn byte_flips_across_the_sample_archive_are_detected() {
    let good = tiny_archive();
    let header = Header::decode(&good, good.len() as u64).unwrap();
    for i in in_sections(&header).step_by(61) {
        let mut bad = good.clone();
        bad[i] ^= 0x80;
        assert!(open_and_verify(bad).is_err(), "flip at {i} went unnoticed");
    }
}

#[test]
fn damage_is_named_by_section_or_tile() {
    let good = tiny_archive();
    let header = Header::decode(&good, good.len() as u64).unwrap();
    let cases = [
        (8usize, "UnsupportedVersion"),
        (100, "header"),
        (usize::try_from(header.metadata.offset).unwrap() + 5, "metadata"),
        (usize::try_from(header.root_dir.offset).unwrap() + 3, "root directory"),
        (usize::try_from(header.data.offset).unwrap() + 20, "tile layer"),
    ];
    for (at, expect) in cases {
        let mut bad = good.clone();
        bad[at] ^= 0x01;
        let msg = match Reader::new(MemorySource::new(bad)) {
            Err(e) => format!("{e:?} {e}"),
            Ok(r) => verify(&r, |_| {}).unwrap().problems.join("; "),
        };
        assert!(msg.contains(expect), "flip at {at}: {msg:?} should name {expect:?}");
    }
}

#[test]
fn truncation_at_any_length_is_an_error() {
    let good = tiny_archive();
    for len in (0..good.len()).step_by(97).chain([good.len() - 1, good.len() - 4, 127, 128, 129]) {
        let result = open_and_verify(good[..len].to_vec());
        assert!(result.is_err(), "truncated to {len} bytes was accepted");
    }
}

#[test]
fn a_damaged_tile_is_an_error_never_garbage() {
    let good = tiny_archive();
    let header = Header::decode(&good, good.len() as u64).unwrap();
    let mut bad = good.clone();
    let last = usize::try_from(header.data.end().unwrap()).unwrap() - 10;
    bad[last] ^= 0xff;
    let reader = Reader::new(MemorySource::new(bad)).unwrap();
    let mut errors = 0;
    let mut ok = 0;
    for lod in 0..4u8 {
        let (nx, ny) = reader.metadata().layers[0].grid_at(lod);
        for y in 0..ny {
            for x in 0..nx {
                for layer in 0..2u8 {
                    let Ok(key) = TileKey::new(layer, lod, x, y) else {
                        continue;
                    };
                    match reader.tile(key) {
                        Err(Error::TileChecksum { key: named, .. }) => {
                            assert_eq!(named, key);
                            errors += 1;
                        }
                        Err(Error::InvalidTile { .. }) => {}
                        Err(e) => panic!("unexpected error {e}"),
                        Ok(_) => ok += 1,
                    }
                }
            }
        }
    }
    assert_eq!(errors, 1, "exactly the damaged tile fails");
    assert!(ok > 50);
}

/// Assembles an archive from parts, as an independent writer following FORMAT.md would.
fn assemble(
    meta_json: &[u8],
    root: &Directory,
    leaves: &[u8],
    data_offset: u64,
    data_len: u64,
    counts: (u64, u64, u64),
) -> (Header, Vec<u8>) {
    let meta = zstd_compress(meta_json, 3).unwrap();
    let root_bytes = zstd_compress(&root.encode_raw(), 3).unwrap();
    let metadata = Section { offset: HEADER_LEN as u64, len: meta.len() as u64 };
    let root_dir = Section { offset: metadata.end().unwrap(), len: root_bytes.len() as u64 };
    let leaf_dirs = Section { offset: root_dir.end().unwrap(), len: leaves.len() as u64 };
    let data = Section { offset: data_offset.max(leaf_dirs.end().unwrap()), len: data_len };
    let header = Header {
        version_major: 1,
        version_minor: 0,
        metadata,
        root_dir,
        leaf_dirs,
        data,
        addressed_tiles: counts.0,
        tile_entries: counts.1,
        tile_contents: counts.2,
        metadata_crc: crc32c(&meta),
        root_dir_crc: crc32c(&root_bytes),
        metadata_compression: Compression::Zstd,
        directory_compression: Compression::Zstd,
    };
    let mut head = header.encode().to_vec();
    head.extend(&meta);
    head.extend(&root_bytes);
    head.extend(leaves);
    (header, head)
}

#[test]
fn offsets_past_4_gib_work_in_a_sparse_file() {
    // Data section starts at 5 GiB; the file is sparse, so nothing close to 5 GiB is written.
    let meta = metadata(vec![layer("texture", 2, 2, 2)]);
    let tile = TileKey::new(0, 0, 1, 1).unwrap();
    let key = tile.archive_key(2).unwrap();
    let payload = b"\x89PNG far away".to_vec();
    let leaf = zstd_compress(
        &Directory::Tiles(vec![Entry { key, run_length: 1, offset: 100, length: payload.len() as u32 }]).encode_raw(),
        3,
    )
    .unwrap();
    let root = Directory::Leaves(vec![LeafPointer {
        first_key: key,
        offset: 0,
        length: leaf.len() as u32,
        crc: crc32c(&leaf),
    }]);
    let data_offset = 5u64 << 30;
    let (header, head) =
        assemble(&meta.to_json(), &root, &leaf, data_offset, 100 + payload.len() as u64 + 4, (1, 1, 1));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.tspack");
    let mut f = std::fs::File::create(&path).unwrap();
    f.write_all(&head).unwrap();
    f.set_len(header.data.end().unwrap()).unwrap();
    let mut blob = payload.clone();
    blob.extend(crc32c(&payload).to_le_bytes());
    std::os::unix::fs::FileExt::write_all_at(&f, &blob, data_offset + 100).unwrap();
    drop(f);
    assert!(std::fs::metadata(&path).unwrap().len() > 5 << 30);

    let file = Reader::new(FileSource::open(&path).unwrap()).unwrap();
    assert_eq!(file.tile(tile).unwrap().unwrap(), payload);
    assert_eq!(file.locate(tile).unwrap().unwrap().offset, data_offset + 100);
    let mmap = Reader::new(MmapSource::open(&path).unwrap()).unwrap();
    assert_eq!(mmap.tile(tile).unwrap().unwrap(), payload);
    assert!(mmap.tile(TileKey::new(0, 0, 0, 0).unwrap()).unwrap().is_none());
    let report = verify(&mmap, |_| {}).unwrap();
    assert!(report.is_ok(), "{:?}", report.problems);
}

#[test]
fn directory_entries_pointing_outside_the_data_section_are_refused() {
    let meta = metadata(vec![layer("texture", 1, 1, 1)]);
    let key = TileKey::new(0, 0, 0, 0).unwrap().archive_key(1).unwrap();
    let root = Directory::Tiles(vec![Entry { key, run_length: 1, offset: 1 << 40, length: 10 }]);
    let (_, mut bytes) = assemble(&meta.to_json(), &root, &[], 0, 14, (1, 1, 1));
    bytes.extend([0u8; 14]);
    let err = Reader::new(MemorySource::new(bytes)).unwrap_err();
    assert!(matches!(err, Error::OutOfBounds { .. }), "{err}");
    assert!(err.to_string().contains("root directory entry 0"), "{err}");
}

#[test]
fn huge_counts_in_small_directories_allocate_nothing() {
    // A root claiming 2^60 entries in a few bytes must fail before allocating.
    let mut raw = Vec::new();
    terrastream_format::write_varint(&mut raw, 1 << 60);
    raw.extend([0u8; 16]);
    let err = Directory::decode_raw(&raw, "root directory", 100, 100).unwrap_err();
    assert!(err.to_string().contains("cannot fit"), "{err}");
}

#[test]
fn other_files_are_not_archives() {
    for bytes in [Vec::new(), b"\x89PNG\r\n\x1a\n".to_vec(), vec![0u8; 20_000], b"TSPACK\r\n\x02\x00".to_vec()] {
        assert!(Reader::new(MemorySource::new(bytes)).is_err());
    }
}

#[test]
fn leaves_stored_out_of_key_order_are_read() {
    // FORMAT.md orders leaf pointers by key, not their bytes: an independent writer may
    // store the second leaf first.
    let meta = metadata(vec![layer("texture", 2, 2, 2)]);
    let tiles: Vec<TileKey> =
        [(1u8, 0u32, 0u32), (0, 1, 1)].iter().map(|&(l, x, y)| TileKey::new(0, l, x, y).unwrap()).collect();
    let keys: Vec<u64> = tiles.iter().map(|t| t.archive_key(2).unwrap()).collect();
    let payloads = [b"coarse".to_vec(), b"fine".to_vec()];
    let mut data = Vec::new();
    let mut leaves_bytes = Vec::new();
    let mut encoded = Vec::new();
    for (key, payload) in keys.iter().zip(&payloads) {
        let entry = Entry { key: *key, run_length: 1, offset: data.len() as u64, length: payload.len() as u32 };
        data.extend(payload);
        data.extend(crc32c(payload).to_le_bytes());
        encoded.push(zstd_compress(&Directory::Tiles(vec![entry]).encode_raw(), 3).unwrap());
    }
    // Second leaf's bytes first.
    leaves_bytes.extend(&encoded[1]);
    leaves_bytes.extend(&encoded[0]);
    let root = Directory::Leaves(vec![
        LeafPointer {
            first_key: keys[0],
            offset: encoded[1].len() as u64,
            length: encoded[0].len() as u32,
            crc: crc32c(&encoded[0]),
        },
        LeafPointer { first_key: keys[1], offset: 0, length: encoded[1].len() as u32, crc: crc32c(&encoded[1]) },
    ]);
    let (_, mut bytes) = assemble(&meta.to_json(), &root, &leaves_bytes, 0, data.len() as u64, (2, 2, 2));
    bytes.extend(&data);
    let reader = Reader::new(MemorySource::new(bytes)).unwrap();
    assert_eq!(&reader.tile(tiles[0]).unwrap().unwrap()[..], b"coarse");
    assert_eq!(&reader.tile(tiles[1]).unwrap().unwrap()[..], b"fine");
    assert!(verify(&reader, |_| {}).unwrap().is_ok());
}
