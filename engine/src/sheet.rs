//! Contact sheets a person can judge at a glance: a grid of equally sized tiles under a header
//! row that names each column, drawn with an 8×8 bitmap font (no font file ships; `curves`
//! writes with it too).

use image::{Rgb, RgbImage};

use crate::Result;

/// Space left free at each side of a column's label, in pixels.
const MARGIN: u32 = 4;

/// The font scale of the header for tiles `tile_width` wide: the largest (up to 3) at which
/// the longest word of any label fits its column.
fn header_scale(tile_width: u32, labels: &[&str]) -> u32 {
    let longest_word = labels
        .iter()
        .flat_map(|l| l.split_whitespace())
        .map(|w| w.chars().count())
        .max()
        .unwrap_or(1)
        .max(1) as u32;
    (tile_width.saturating_sub(2 * MARGIN) / (8 * longest_word)).clamp(1, 3)
}

/// `label` broken at spaces into lines of at most `width` characters (a longer word keeps its
/// own line and is clipped at the column's edge).
fn wrap(label: &str, width: usize) -> Vec<String> {
    let mut lines: Vec<String> = Vec::new();
    for word in label.split_whitespace() {
        match lines.last_mut() {
            Some(line) if line.chars().count() + 1 + word.chars().count() <= width => {
                line.push(' ');
                line.push_str(word);
            }
            _ => lines.push(word.to_string()),
        }
    }
    lines
}

/// Writes `text` at (x, y) in white, each font pixel a `scale`² block, clipped at `max_x`;
/// characters outside ASCII are drawn as `?`.
pub(crate) fn draw_text(
    img: &mut RgbImage,
    (x, y): (u32, u32),
    max_x: u32,
    text: &str,
    scale: u32,
) {
    for (i, ch) in text.chars().enumerate() {
        let glyph = font8x8::legacy::BASIC_LEGACY[if ch.is_ascii() {
            ch as usize
        } else {
            b'?' as usize
        }];
        for (gy, bits) in glyph.iter().enumerate() {
            for gx in 0..8 {
                if bits >> gx & 1 == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let px = x + (i as u32 * 8 + gx) * scale + dx;
                        let py = y + gy as u32 * scale + dy;
                        if px < max_x.min(img.width()) && py < img.height() {
                            img.put_pixel(px, py, Rgb([255, 255, 255]));
                        }
                    }
                }
            }
        }
    }
}

/// A grid of `rows` (each a row of tiles, all the size of the first) under a dark header that
/// names each column.
pub fn labelled_grid(labels: &[&str], rows: &[Vec<RgbImage>]) -> Result<RgbImage> {
    let first = rows
        .first()
        .and_then(|r| r.first())
        .ok_or_else(|| crate::EngineError::config("contact sheet", "needs at least one tile"))?;
    let (w, h) = first.dimensions();
    let cols = labels
        .len()
        .max(rows.iter().map(Vec::len).max().unwrap_or(0)) as u32;
    let scale = header_scale(w, labels);
    let per_line = (w.saturating_sub(2 * MARGIN) / (8 * scale)).max(1) as usize;
    let wrapped: Vec<Vec<String>> = labels.iter().map(|l| wrap(l, per_line)).collect();
    let line_height = 8 * scale + 2;
    let lines = wrapped.iter().map(Vec::len).max().unwrap_or(0).max(1) as u32;
    let header = lines * line_height + 2 * MARGIN - 2;
    let mut img = RgbImage::from_pixel(cols * w, header + h * rows.len() as u32, Rgb([24, 24, 24]));
    for (c, label) in wrapped.iter().enumerate() {
        for (l, line) in label.iter().enumerate() {
            draw_text(
                &mut img,
                (c as u32 * w + MARGIN, MARGIN + l as u32 * line_height),
                (c as u32 + 1) * w - MARGIN,
                line,
                scale,
            );
        }
    }
    for (r, row) in rows.iter().enumerate() {
        for (c, tile) in row.iter().enumerate() {
            image::imageops::replace(
                &mut img,
                tile,
                (c as u32 * w) as i64,
                (header + r as u32 * h) as i64,
            );
        }
    }
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_names_columns_above_the_tiles() {
        let red = RgbImage::from_pixel(64, 32, Rgb([200, 0, 0]));
        let blue = RgbImage::from_pixel(64, 32, Rgb([0, 0, 200]));
        let img = labelled_grid(
            &["style", "ours"],
            &[vec![red.clone(), blue.clone()], vec![blue, red]],
        )
        .unwrap();
        let header = img.height() - 64;
        assert!(header >= 16, "a header of {header} px");
        // Tiles under the header, in order.
        assert_eq!(img.get_pixel(10, header + 5), &Rgb([200, 0, 0]));
        assert_eq!(img.get_pixel(70, header + 5), &Rgb([0, 0, 200]));
        assert_eq!(img.get_pixel(70, header + 40), &Rgb([200, 0, 0]));
        // Each label drew white pixels inside its own column's header, and only there.
        let white = |x0: u32, x1: u32| {
            (x0..x1)
                .flat_map(|x| (0..header).map(move |y| (x, y)))
                .filter(|&(x, y)| img.get_pixel(x, y) == &Rgb([255, 255, 255]))
                .count()
        };
        assert!(white(0, 64) > 20 && white(64, 128) > 20);
        assert!(labelled_grid(&["a"], &[]).is_err());
    }

    #[test]
    fn long_labels_wrap_inside_their_column() {
        let tile = RgbImage::from_pixel(128, 32, Rgb([0, 0, 0]));
        let labels = ["photoreal render", "NeRF -> AdaIN", "stylized NeRF (ours)"];
        let img = labelled_grid(&labels, &[vec![tile; 3]]).unwrap();
        let header = img.height() - 32;
        let white_in = |x0: u32, x1: u32, y0: u32, y1: u32| {
            (x0..x1)
                .flat_map(|x| (y0..y1).map(move |y| (x, y)))
                .filter(|&(x, y)| img.get_pixel(x, y) == &Rgb([255, 255, 255]))
                .count()
        };
        // Nothing within the margin on either side of a column boundary: labels never touch.
        for edge in [128, 256] {
            assert_eq!(white_in(edge - MARGIN, edge + MARGIN, 0, header), 0);
        }
        // "photoreal render" does not fit one 120-pixel line at scale 1: a second line holds
        // "render".
        assert_eq!(wrap("photoreal render", 15), ["photoreal", "render"]);
        assert!(white_in(0, 128, MARGIN + 10, header) > 20);
        assert_eq!(wrap("a b c", 3), ["a b", "c"]);
    }
}
