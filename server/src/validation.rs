//! Submission-time validation of job inputs without the engine: dataset tar archives (member
//! paths, types, sizes and counts; a parseable `transforms.json`, `transforms_train.json` or
//! `poses_bounds.npy` whose images are present) and style images (decode within limits).
//! Errors are human-readable descriptions; callers attach the field name.

use crate::config::Limits;
use std::collections::HashSet;
use std::io::Read;
use std::path::{Component, Path};
use stylenerf_plan::scene_format::{find_scene, SceneFormat, MAX_SCENE_DEPTH, NO_SCENE};

/// What a valid dataset archive holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetSummary {
    /// `nerfstudio`, `blender` or `llff`.
    pub format: &'static str,
    /// Path of the scene file inside the archive.
    pub scene_file: String,
    pub frames: usize,
    pub members: u64,
}

impl std::fmt::Display for DatasetSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} scene ({}): {} frames, {} archive members",
            self.format, self.scene_file, self.frames, self.members
        )
    }
}

const IMAGE_EXTENSIONS: [&str; 7] = ["png", "jpg", "jpeg", "PNG", "JPG", "JPEG", "webp"];
/// Largest scene file read into memory.
const MAX_SCENE_FILE_BYTES: u64 = 64 << 20;

/// Checks a dataset tar archive read from `reader` (buffered here).
pub fn validate_dataset_archive(
    reader: impl Read,
    limits: &Limits,
) -> Result<DatasetSummary, String> {
    let mut scene_files: Vec<(String, Vec<u8>)> = Vec::new();
    let walked = walk_archive(reader, limits, |path, size, entry| {
        let file_name = path.rsplit('/').next().unwrap_or("");
        let candidate = SceneFormat::of_marker(file_name).is_some()
            && path.matches('/').count() <= MAX_SCENE_DEPTH;
        if candidate {
            if size > MAX_SCENE_FILE_BYTES {
                return Err(format!("scene file {path:?} is larger than 64 MiB"));
            }
            let mut content = Vec::with_capacity(size as usize);
            entry
                .read_to_end(&mut content)
                .map_err(|e| format!("member {path:?}: {e}"))?;
            scene_files.push((path.to_string(), content));
        }
        Ok(())
    })?;
    let (members, count) = (walked.members, walked.count);
    // As the worker finds it (the catalogue's rule).
    let (format, scene_path) = find_scene(scene_files.iter().map(|(path, _)| path.as_str()))
        .ok_or_else(|| NO_SCENE.to_string())?;
    let scene_path = scene_path.to_string();
    let content = scene_files
        .into_iter()
        .find(|(path, _)| *path == scene_path)
        .map(|(_, content)| content)
        .unwrap_or_default();
    let dir = scene_path
        .rsplit_once('/')
        .map(|(d, _)| d.to_string())
        .unwrap_or_default();
    let frames = if format == SceneFormat::Llff {
        check_poses_bounds(&content, &dir, &members, limits)
    } else {
        check_transforms(&content, &dir, &members, limits)
    }
    .map_err(|why| format!("{scene_path}: {why}"))?;
    Ok(DatasetSummary {
        format: format.name(),
        scene_file: scene_path,
        frames,
        members: count,
    })
}

/// The members of a checked archive.
pub struct Walked {
    /// Every member path, relative and `/`-separated.
    pub members: HashSet<String>,
    /// How many members there are.
    pub count: u64,
}

/// Reads a tar archive from `reader` (buffered here), checking every member: no compression,
/// relative paths inside the archive, only regular files and folders, each path once, counts
/// and sizes within `limits`. `on_file(path, size, entry)` sees each regular file.
pub fn walk_archive(
    reader: impl Read,
    limits: &Limits,
    mut on_file: impl FnMut(&str, u64, &mut dyn Read) -> Result<(), String>,
) -> Result<Walked, String> {
    let mut reader = std::io::BufReader::new(reader);
    let head = std::io::BufRead::fill_buf(&mut reader).map_err(|e| e.to_string())?;
    if let Some(kind) = compression(head) {
        return Err(format!(
            "a {kind} file: compressed archives are not supported; send an uncompressed tar \
             (tar -cf scene.tar -C my_scene .)"
        ));
    }
    let mut archive = tar::Archive::new(reader);
    let entries = archive
        .entries()
        .map_err(|e| format!("not a tar archive: {}", printable(&e.to_string())))?;
    let mut members: HashSet<String> = HashSet::new();
    let mut count = 0u64;
    let mut total = 0u64;
    for entry in entries {
        let mut entry = entry.map_err(|e| {
            format!(
                "corrupt or not a tar archive: {}",
                printable(&e.to_string())
            )
        })?;
        let kind = entry.header().entry_type();
        if kind.is_pax_global_extensions() {
            continue;
        }
        let raw_path = printable(&String::from_utf8_lossy(&entry.path_bytes()));
        let path = match normalize_member_path(&raw_path) {
            // `tar -C dir .` starts with the folder itself, `./`.
            Ok(None) if kind.is_dir() => continue,
            Ok(None) => return Err(format!("member {raw_path:?}: empty path")),
            Ok(Some(path)) => path,
            Err(why) => return Err(format!("member {raw_path:?}: {why}")),
        };
        if !(kind.is_file() || kind.is_dir() || kind.is_contiguous()) {
            return Err(format!(
                "member {raw_path:?}: only regular files and directories are allowed, not {}",
                describe_entry_type(kind)
            ));
        }
        count += 1;
        if count > limits.max_archive_members {
            return Err(format!(
                "more than {} archive members",
                limits.max_archive_members
            ));
        }
        let size = entry.size();
        if size > limits.max_member_bytes {
            return Err(format!(
                "member {raw_path:?} is {size} bytes, more than the limit of {}",
                limits.max_member_bytes
            ));
        }
        total += size;
        if total > limits.max_dataset_bytes {
            return Err(format!(
                "members add up to more than {} bytes",
                limits.max_dataset_bytes
            ));
        }
        if !kind.is_dir() {
            on_file(&path, size, &mut entry)?;
        }
        // Unpacking keeps the last of two members with one path, while this check would
        // have read the first.
        if !members.insert(path) && !kind.is_dir() {
            return Err(format!("member {raw_path:?} appears twice"));
        }
    }
    Ok(Walked { members, count })
}

/// The compression format a file starting with `head` is in, if any.
fn compression(head: &[u8]) -> Option<&'static str> {
    const MAGIC: [(&[u8], &str); 4] = [
        (&[0x1f, 0x8b], "gzip"),
        (b"BZh", "bzip2"),
        (&[0xfd, b'7', b'z', b'X', b'Z', 0], "xz"),
        (&[0x28, 0xb5, 0x2f, 0xfd], "zstd"),
    ];
    MAGIC
        .iter()
        .find(|(magic, _)| head.starts_with(magic))
        .map(|(_, kind)| *kind)
}

/// `text` with anything but printable characters replaced, and cut to 200 characters: archive
/// errors quote bytes from the archive, which may be binary.
fn printable(text: &str) -> String {
    let mut out: String = text
        .chars()
        .map(|c| if c.is_control() { '\u{fffd}' } else { c })
        .take(200)
        .collect();
    if text.chars().count() > 200 {
        out.push('…');
    }
    out
}

/// A member path made relative and `/`-separated (`None` for the archive's root, `./`), or
/// why it is not acceptable.
fn normalize_member_path(raw: &str) -> Result<Option<String>, &'static str> {
    if raw.contains('\\') {
        return Err("backslashes are not allowed in paths");
    }
    let mut parts = Vec::new();
    for component in Path::new(raw).components() {
        match component {
            Component::Normal(part) => parts.push(part.to_string_lossy().into_owned()),
            Component::CurDir => {}
            Component::ParentDir => return Err("`..` is not allowed in paths"),
            Component::RootDir | Component::Prefix(_) => {
                return Err("absolute paths are not allowed")
            }
        }
    }
    Ok((!parts.is_empty()).then(|| parts.join("/")))
}

fn describe_entry_type(kind: tar::EntryType) -> &'static str {
    if kind.is_symlink() {
        "a symbolic link"
    } else if kind.is_hard_link() {
        "a hard link"
    } else if kind.is_character_special() || kind.is_block_special() {
        "a device"
    } else if kind.is_fifo() {
        "a FIFO"
    } else {
        "this entry type"
    }
}

/// Resolves `file_path` of a frame (relative to the scene file's directory) to an archive
/// member, trying the usual image extensions when it has none that matches.
fn image_present(dir: &str, file_path: &str, members: &HashSet<String>) -> bool {
    let joined = if dir.is_empty() {
        file_path.to_string()
    } else {
        format!("{dir}/{file_path}")
    };
    let mut parts: Vec<&str> = Vec::new();
    for part in joined.split('/') {
        match part {
            "" | "." => {}
            ".." => {
                if parts.pop().is_none() {
                    return false;
                }
            }
            p => parts.push(p),
        }
    }
    let path = parts.join("/");
    members.contains(&path)
        || IMAGE_EXTENSIONS
            .iter()
            .any(|ext| members.contains(&format!("{path}.{ext}")))
}

fn check_transforms(
    content: &[u8],
    dir: &str,
    members: &HashSet<String>,
    limits: &Limits,
) -> Result<usize, String> {
    let value: serde_json::Value =
        serde_json::from_slice(content).map_err(|e| format!("not valid JSON: {e}"))?;
    let obj = value.as_object().ok_or("must be a JSON object")?;
    let frames = obj
        .get("frames")
        .and_then(|f| f.as_array())
        .ok_or("has no `frames` array")?;
    if frames.is_empty() {
        return Err("`frames` is empty".into());
    }
    if frames.len() as u64 > limits.max_frames {
        return Err(format!(
            "{} frames, more than the limit of {}",
            frames.len(),
            limits.max_frames
        ));
    }
    let has_intrinsics = |o: &serde_json::Map<String, serde_json::Value>| {
        ["camera_angle_x", "fl_x"]
            .iter()
            .any(|k| o.get(*k).is_some_and(|v| v.is_number()))
    };
    for (i, frame) in frames.iter().enumerate() {
        let frame = frame
            .as_object()
            .ok_or_else(|| format!("frames[{i}] is not an object"))?;
        let matrix_ok = frame
            .get("transform_matrix")
            .and_then(|m| m.as_array())
            .is_some_and(|rows| {
                (rows.len() == 3 || rows.len() == 4)
                    && rows.iter().all(|row| {
                        row.as_array().is_some_and(|r| {
                            r.len() == 4 && r.iter().all(|x| x.as_f64().is_some_and(f64::is_finite))
                        })
                    })
            });
        if !matrix_ok {
            return Err(format!(
                "frames[{i}].transform_matrix must be a 4×4 or 3×4 matrix of finite numbers"
            ));
        }
        if !has_intrinsics(obj) && !has_intrinsics(frame) {
            return Err(format!(
                "no camera intrinsics for frames[{i}] (camera_angle_x or fl_x)"
            ));
        }
        let file_path = frame
            .get("file_path")
            .and_then(|p| p.as_str())
            .ok_or_else(|| format!("frames[{i}].file_path is missing"))?;
        if file_path.starts_with('/') || file_path.contains('\\') {
            return Err(format!(
                "frames[{i}].file_path {file_path:?} must be a relative path with `/` separators"
            ));
        }
        if !image_present(dir, file_path, members) {
            return Err(format!(
                "frames[{i}].file_path {file_path:?} is not in the archive"
            ));
        }
    }
    Ok(frames.len())
}

/// Checks an LLFF `poses_bounds.npy` (float N×17) and that `images/` next to it holds at least
/// N images.
fn check_poses_bounds(
    content: &[u8],
    dir: &str,
    members: &HashSet<String>,
    limits: &Limits,
) -> Result<usize, String> {
    // The engine's own parser: what it refuses, the upload is refused for.
    let matrix = stylenerf_plan::npy::parse_matrix(content)
        .map_err(|e| format!("{}: {}", e.field, e.reason))?;
    let n = match (matrix.rows, matrix.cols) {
        (n, 17) if n > 0 => n,
        (rows, cols) => return Err(format!("shape must be (N, 17), not ({rows}, {cols})")),
    };
    if n as u64 > limits.max_frames {
        return Err(format!(
            "{n} poses, more than the limit of {}",
            limits.max_frames
        ));
    }
    let images_dir = if dir.is_empty() {
        "images/".to_string()
    } else {
        format!("{dir}/images/")
    };
    let images = members
        .iter()
        .filter(|m| {
            m.starts_with(&images_dir)
                && m.rsplit_once('.')
                    .is_some_and(|(_, ext)| IMAGE_EXTENSIONS.contains(&ext))
        })
        .count();
    if images < n {
        return Err(format!("{n} poses but {images} images in {images_dir}"));
    }
    Ok(n)
}

/// What a valid style image is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImageSummary {
    pub format: &'static str,
    pub width: u32,
    pub height: u32,
}

impl ImageSummary {
    /// File extension for the stored copy.
    pub fn extension(&self) -> &'static str {
        self.format
    }
}

impl std::fmt::Display for ImageSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} image {}x{}", self.format, self.width, self.height)
    }
}

/// Checks that `bytes` is a PNG, JPEG, GIF or WebP image that decodes within the limits.
pub fn validate_style_image(bytes: &[u8], limits: &Limits) -> Result<ImageSummary, String> {
    let format = image::guess_format(bytes)
        .map_err(|_| "not an image (PNG, JPEG, GIF or WebP expected)".to_string())?;
    let name = match format {
        image::ImageFormat::Png => "png",
        image::ImageFormat::Jpeg => "jpg",
        image::ImageFormat::Gif => "gif",
        image::ImageFormat::WebP => "webp",
        other => return Err(format!("unsupported image format {other:?}")),
    };
    let mut image_limits = image::Limits::default();
    image_limits.max_image_width = Some(limits.max_style_dimension);
    image_limits.max_image_height = Some(limits.max_style_dimension);
    let mut reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), format);
    reader.limits(image_limits);
    let decoded = reader.decode().map_err(|e| match e {
        image::ImageError::Limits(_) => format!(
            "image is larger than {0}x{0} pixels",
            limits.max_style_dimension
        ),
        e => format!("cannot decode the {name} image: {e}"),
    })?;
    Ok(ImageSummary {
        format: name,
        width: decoded.width(),
        height: decoded.height(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    use stylenerf_testkit::tar_of as archive;

    const TRANSFORMS: &[u8] = br#"{"camera_angle_x": 0.7, "frames": [
        {"file_path": "./train/r_0", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}
    ]}"#;

    #[test]
    fn accepts_a_blender_scene() {
        let tar = archive(&[
            ("scene/transforms_train.json", TRANSFORMS),
            ("scene/train/r_0.png", b"x"),
        ]);
        let summary = validate_dataset_archive(&tar[..], &Limits::default()).unwrap();
        assert_eq!(summary.format, "blender");
        assert_eq!(summary.frames, 1);
    }

    #[test]
    fn rejects_missing_images_and_scene_files() {
        let tar = archive(&[("transforms.json", TRANSFORMS)]);
        let err = validate_dataset_archive(&tar[..], &Limits::default()).unwrap_err();
        assert!(err.contains("not in the archive"), "{err}");
        let tar = archive(&[("a.png", b"x")]);
        let err = validate_dataset_archive(&tar[..], &Limits::default()).unwrap_err();
        assert!(err.contains("no scene file"), "{err}");
    }

    #[test]
    fn normalizes_member_paths() {
        assert_eq!(
            normalize_member_path("./a/b.png").unwrap().as_deref(),
            Some("a/b.png")
        );
        assert_eq!(normalize_member_path("./").unwrap(), None);
        assert!(normalize_member_path("/etc/passwd").is_err());
        assert!(normalize_member_path("a/../../b").is_err());
    }

    #[test]
    fn checks_llff_poses() {
        let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 17), }";
        let mut npy = b"\x93NUMPY\x01\x00".to_vec();
        npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
        npy.extend_from_slice(header.as_bytes());
        npy.extend_from_slice(&[0u8; 2 * 17 * 8]);
        let ok = archive(&[
            ("poses_bounds.npy", &npy),
            ("images/a.jpg", b"x"),
            ("images/b.jpg", b"x"),
        ]);
        assert_eq!(
            validate_dataset_archive(&ok[..], &Limits::default())
                .unwrap()
                .frames,
            2
        );
        let short = archive(&[("poses_bounds.npy", &npy), ("images/a.jpg", b"x")]);
        assert!(validate_dataset_archive(&short[..], &Limits::default()).is_err());
        // Refused as the worker's reader would refuse it: data beyond the shape, a wrong shape.
        let mut long = npy.clone();
        long.extend_from_slice(&[0u8; 8]);
        let e = validate_dataset_archive(
            &archive(&[("poses_bounds.npy", &long), ("images/a.jpg", b"x")])[..],
            &Limits::default(),
        )
        .unwrap_err();
        assert!(e.contains("data") && e.contains("bytes"), "{e}");
        let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 16), }";
        let mut narrow = b"\x93NUMPY\x01\x00".to_vec();
        narrow.extend_from_slice(&(header.len() as u16).to_le_bytes());
        narrow.extend_from_slice(header.as_bytes());
        narrow.extend_from_slice(&[0u8; 2 * 16 * 8]);
        let e = validate_dataset_archive(
            &archive(&[("poses_bounds.npy", &narrow), ("images/a.jpg", b"x")])[..],
            &Limits::default(),
        )
        .unwrap_err();
        assert!(e.contains("(N, 17)") && e.contains("(2, 16)"), "{e}");
    }

    /// Whatever the bytes, validation answers with a summary or a printable reason, never a
    /// panic. proptest's `PROPTEST_CASES` cases per property (256 unless set).
    mod properties {
        use super::*;
        use proptest::prelude::*;
        fn printable(reason: &str) -> bool {
            !reason.chars().any(char::is_control)
        }

        fn damage(mut bytes: Vec<u8>, flips: &[(prop::sample::Index, u8)], cut: usize) -> Vec<u8> {
            for (at, byte) in flips {
                let i = at.index(bytes.len());
                bytes[i] = *byte;
            }
            bytes.truncate(cut.min(bytes.len()));
            bytes
        }

        proptest! {
            #[test]
            fn archives(bytes in prop::collection::vec(any::<u8>(), 0..2048),
                        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
                        cut in 0usize..4096) {
                let valid = archive(&[
                    ("scene/transforms_train.json", TRANSFORMS),
                    ("scene/train/r_0.png", b"x"),
                ]);
                for data in [bytes, damage(valid, &flips, cut)] {
                    if let Err(reason) = validate_dataset_archive(&data[..], &Limits::default()) {
                        prop_assert!(printable(&reason), "{:?}", reason);
                    }
                }
            }

            #[test]
            fn style_images(bytes in prop::collection::vec(any::<u8>(), 0..2048),
                            flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
                            cut in 0usize..4096) {
                let mut png = std::io::Cursor::new(Vec::new());
                image::RgbImage::new(9, 7)
                    .write_to(&mut png, image::ImageFormat::Png)
                    .unwrap();
                for data in [bytes, damage(png.into_inner(), &flips, cut)] {
                    if let Ok(summary) = validate_style_image(&data, &Limits::default()) {
                        prop_assert!(summary.width > 0 && summary.height > 0);
                    }
                }
            }
        }
    }
}
