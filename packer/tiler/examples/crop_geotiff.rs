//! Cuts a window out of a single-band int16 GeoTIFF, keeping its georeference, and
//! writes it Deflate-compressed: how the committed test DEMs were made.
//!
//! `cargo run -p terrastream-tiler --example crop_geotiff -- IN OUT X Y W H [--ocean-nodata]`
//! (`--ocean-nodata` turns samples <= 0 into nodata, making a sparse pyramid.)
#![allow(clippy::print_stdout)]

use std::process::ExitCode;

use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{Compression, DeflateLevel, TiffEncoder, colortype::GrayI16};
use tiff::tags::Tag;

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("crop_geotiff: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 6 {
        return Err("usage: IN OUT X Y W H [--ocean-nodata]".into());
    }
    let [x0, y0, w, h] = [2, 3, 4, 5].map(|i| args[i].parse::<u32>().unwrap_or(0));
    let ocean = args.iter().any(|a| a == "--ocean-nodata");
    let mut decoder = Decoder::new(std::fs::File::open(&args[0])?)?;
    let (width, _) = decoder.dimensions()?;
    let f64s = |d: &mut Decoder<std::fs::File>, t: u16| -> Option<Vec<f64>> {
        d.find_tag(Tag::Unknown(t)).ok()??.into_f64_vec().ok()
    };
    let scale = f64s(&mut decoder, 33550).ok_or("no ModelPixelScale")?;
    let mut tiepoint = f64s(&mut decoder, 33922).ok_or("no ModelTiepoint")?;
    let keys: Vec<u16> = decoder
        .find_tag(Tag::Unknown(34735))?
        .ok_or("no GeoKeyDirectory")?
        .into_u64_vec()?
        .into_iter()
        .map(|k| u16::try_from(k).unwrap_or(0))
        .collect();
    // The GeoKeys' parameters: keys of type double or ASCII point into these two tags.
    let doubles = f64s(&mut decoder, 34736);
    let ascii = decoder.find_tag(Tag::Unknown(34737))?.and_then(|v| v.into_string().ok());
    let nodata = decoder.find_tag(Tag::Unknown(42113))?.and_then(|v| v.into_string().ok());
    let DecodingResult::I16(data) = decoder.read_image()? else { return Err("not int16".into()) };
    let nodata_value = nodata.as_deref().and_then(|s| s.trim_matches(char::from(0)).trim().parse::<i16>().ok());
    let fill = nodata_value.unwrap_or(-32767);
    let crop: Vec<i16> = (y0..y0 + h)
        .flat_map(|y| (x0..x0 + w).map(move |x| (x, y)))
        .map(|(x, y)| data[(y as usize) * (width as usize) + x as usize])
        .map(|v| if ocean && v <= 0 { fill } else { v })
        .collect();
    tiepoint[3] += f64::from(x0) * scale[0];
    tiepoint[4] -= f64::from(y0) * scale[1];
    let file = std::fs::File::create(&args[1])?;
    let mut tiff = TiffEncoder::new(file)?.with_compression(Compression::Deflate(DeflateLevel::Best));
    let mut image = tiff.new_image::<GrayI16>(w, h)?;
    let enc = image.encoder();
    enc.write_tag(Tag::Unknown(33550), &scale[..])?;
    enc.write_tag(Tag::Unknown(33922), &tiepoint[..])?;
    enc.write_tag(Tag::Unknown(34735), &keys[..])?;
    if let Some(doubles) = &doubles {
        enc.write_tag(Tag::Unknown(34736), &doubles[..])?;
    }
    if let Some(ascii) = &ascii {
        enc.write_tag(Tag::Unknown(34737), ascii.trim_end_matches(char::from(0)))?;
    }
    if ocean || nodata.is_some() {
        enc.write_tag(Tag::Unknown(42113), fill.to_string().as_str())?;
    }
    image.write_data(&crop)?;
    println!("wrote {} ({w}x{h} from ({x0}, {y0}))", args[1]);
    Ok(())
}
