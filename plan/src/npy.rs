//! A minimal reader and writer for NumPy `.npy` files holding a 2-D little-endian matrix in C
//! order: LLFF's `poses_bounds.npy` (float) and nerfstudio depth maps (float or uint16, shape
//! (H, W) or (H, W, 1)). The engine reads scenes with it and the coordinator validates uploads
//! with it, so an accepted upload parses the same on a worker.
//!
//! Format: the magic `\x93NUMPY`, a version byte pair, the header length (u16 in version 1,
//! u32 in versions 2 and 3), an ASCII Python dict literal such as
//! `{'descr': '<f8', 'fortran_order': False, 'shape': (20, 17), }`, then the raw data.

use crate::SettingError;

const MAGIC: &[u8] = b"\x93NUMPY";

/// A row-major matrix of f64 values.
#[derive(Debug, Clone, PartialEq)]
pub struct Matrix {
    pub rows: usize,
    pub cols: usize,
    pub data: Vec<f64>,
}

impl Matrix {
    pub fn row(&self, r: usize) -> &[f64] {
        &self.data[r * self.cols..(r + 1) * self.cols]
    }
}

/// Parses a 2-D `<f8`, `<f4` or `<u2` array (a trailing axis of length 1 is dropped). Errors
/// name the part of the file that is wrong (`header`, `descr`, `fortran_order`, `shape`,
/// `data`).
pub fn parse_matrix(bytes: &[u8]) -> Result<Matrix, SettingError> {
    let err = |field: &str, reason: String| SettingError::new(field, reason);
    if !bytes.starts_with(MAGIC) || bytes.len() < 10 {
        return Err(err("header", "not a NumPy .npy file (bad magic)".into()));
    }
    let (header_len, header_start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(err("header", format!("unsupported .npy version {v}"))),
    };
    let data_start = header_start + header_len;
    let header = bytes
        .get(header_start..data_start)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| err("header", "truncated or not text".into()))?;

    let descr = dict_value(header, "descr")
        .and_then(quoted)
        .ok_or_else(|| err("descr", format!("missing in header {header:?}")))?;
    let item = match descr {
        "<f8" => 8,
        "<f4" => 4,
        "<u2" => 2,
        other => {
            return Err(err(
                "descr",
                format!(
                    "unsupported dtype `{other}`: expected little-endian float64 `<f8`, \
                     float32 `<f4` or uint16 `<u2`"
                ),
            ))
        }
    };
    match dict_value(header, "fortran_order") {
        Some(v) if v.starts_with("False") => {}
        Some(v) if v.starts_with("True") => {
            return Err(err(
                "fortran_order",
                "Fortran-ordered arrays are not supported".into(),
            ))
        }
        _ => {
            return Err(err(
                "fortran_order",
                format!("missing in header {header:?}"),
            ))
        }
    }
    let shape = dict_value(header, "shape").and_then(tuple).ok_or_else(|| {
        err(
            "shape",
            format!("missing or malformed in header {header:?}"),
        )
    })?;
    let (&[rows, cols] | &[rows, cols, 1]) = &shape[..] else {
        return Err(err(
            "shape",
            format!("expected a 2-D array, found shape {shape:?}"),
        ));
    };
    let expected = rows
        .checked_mul(cols)
        .and_then(|n| n.checked_mul(item))
        .ok_or_else(|| err("shape", format!("shape {shape:?} is too large")))?;
    let raw = &bytes[data_start.min(bytes.len())..];
    if raw.len() != expected {
        return Err(err(
            "data",
            format!(
                "shape {shape:?} needs {expected} bytes of data, the file has {}",
                raw.len()
            ),
        ));
    }
    let data = match item {
        8 => raw
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8-byte chunk")))
            .collect(),
        4 => raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4-byte chunk")) as f64)
            .collect(),
        _ => raw
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]) as f64)
            .collect(),
    };
    Ok(Matrix { rows, cols, data })
}

/// Encodes a 2-D `<f8` array (version 1.0 header padded to 64 bytes).
pub fn encode_matrix(m: &Matrix) -> Vec<u8> {
    assert_eq!(
        m.data.len(),
        m.rows * m.cols,
        "matrix data matches its shape"
    );
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, {}), }}",
        m.rows, m.cols
    );
    while !(MAGIC.len() + 4 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = MAGIC.to_vec();
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for x in &m.data {
        bytes.extend_from_slice(&x.to_le_bytes());
    }
    bytes
}

/// The text following `'key':` in a Python dict literal.
fn dict_value<'h>(header: &'h str, key: &str) -> Option<&'h str> {
    let at = header.find(&format!("'{key}'"))? + key.len() + 2;
    header[at..]
        .trim_start()
        .strip_prefix(':')
        .map(str::trim_start)
}

/// The contents of a leading '...' string.
fn quoted(s: &str) -> Option<&str> {
    let s = s.strip_prefix('\'')?;
    Some(&s[..s.find('\'')?])
}

/// The integers of a leading (a, b, ...) tuple.
fn tuple(s: &str) -> Option<Vec<usize>> {
    let s = s.strip_prefix('(')?;
    s[..s.find(')')?]
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| t.trim_end_matches('L').parse().ok())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_header_alignment() {
        let m = Matrix {
            rows: 2,
            cols: 3,
            data: vec![1.0, -2.5, 3.0, 4.0, 5.0, 1e-9],
        };
        let bytes = encode_matrix(&m);
        assert_eq!((bytes.len() - 6 * 8) % 64, 0);
        assert_eq!(parse_matrix(&bytes).unwrap(), m);
        let e = parse_matrix(&bytes[..bytes.len() - 8]).unwrap_err();
        assert_eq!(e.field, "data");
        assert_eq!(parse_matrix(b"PK\x03\x04").unwrap_err().field, "header");
    }

    #[test]
    fn reads_float32_arrays() {
        let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 2), }\n";
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&[1, 0]);
        bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        bytes.extend_from_slice(&1.5f32.to_le_bytes());
        bytes.extend_from_slice(&(-2.0f32).to_le_bytes());
        let m = parse_matrix(&bytes).unwrap();
        assert_eq!((m.rows, m.cols, m.data), (1, 2, vec![1.5, -2.0]));
    }
}
