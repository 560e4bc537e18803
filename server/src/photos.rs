//! Submission-time validation of a scene without camera poses (`UPLOAD_KIND_PHOTOS`), for a
//! job that starts with the `poses` stage: a tar archive of photos, its members checked as a
//! dataset archive's are, the photos found by the catalogue's rule
//! ([`find_photos`]) and every photo's header read; or one video file, recognised by its
//! container's signature. What a worker would refuse is refused here, naming the member.

use std::io::{Read, Seek};
use std::path::Path;

use stylenerf_plan::scene_format::{find_photos, MIN_PHOTOS, PHOTO_EXTENSIONS};
use stylenerf_plan::Source;

use crate::config::Limits;
use crate::validation::walk_archive;

/// What a valid upload of photos holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PhotosSummary {
    /// `Photos` (an archive) or `Video`.
    pub source: Source,
    /// The extension to store it with: `tar`, or the video container's.
    pub extension: &'static str,
    /// Photos in the folder that holds them (0 for a video).
    pub photos: usize,
    /// That folder, relative to the archive's root (`""` for the root itself).
    pub folder: String,
}

impl std::fmt::Display for PhotosSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.source {
            Source::Video => write!(f, "{} video", self.extension),
            _ if self.folder.is_empty() => write!(f, "{} photos", self.photos),
            _ => write!(f, "{} photos in {}/", self.photos, self.folder),
        }
    }
}

/// Checks the upload of photos at `path`.
pub fn validate_photos(path: &Path, limits: &Limits) -> Result<PhotosSummary, String> {
    let mut file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut head = Vec::with_capacity(512);
    (&mut file)
        .take(512)
        .read_to_end(&mut head)
        .map_err(|e| e.to_string())?;
    if let Some(extension) = video_container(&head) {
        return Ok(PhotosSummary {
            source: Source::Video,
            extension,
            photos: 0,
            folder: String::new(),
        });
    }
    if head.len() < 262 || &head[257..262] != b"ustar" {
        return Err(
            "neither a tar archive of photos nor a video (MP4, MOV, MKV, WebM, AVI or MPEG-TS); \
             archive a folder of photos with `tar -cf photos.tar -C my_photos .`"
                .into(),
        );
    }
    file.rewind().map_err(|e| e.to_string())?;
    let walked = walk_archive(file, limits, |member, _size, entry| {
        let ext = member.rsplit_once('.').map(|(_, e)| e.to_ascii_lowercase());
        if !ext.is_some_and(|e| PHOTO_EXTENSIONS.contains(&e.as_str())) {
            return Ok(());
        }
        let mut bytes = Vec::new();
        entry
            .read_to_end(&mut bytes)
            .map_err(|e| format!("member {member:?}: {e}"))?;
        let (width, height) = image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| format!("member {member:?}: {e}"))?
            .into_dimensions()
            .map_err(|e| format!("member {member:?}: not a readable PNG or JPEG photo: {e}"))?;
        if width < 16 || height < 16 {
            return Err(format!(
                "member {member:?}: {width}x{height} pixels is too small to match features in"
            ));
        }
        Ok(())
    })?;
    match find_photos(walked.members.iter().map(String::as_str)) {
        Some((folder, photos)) if photos >= MIN_PHOTOS => Ok(PhotosSummary {
            source: Source::Photos,
            extension: "tar",
            photos,
            folder: folder.to_string(),
        }),
        found => Err(format!(
            "{} PNG/JPEG photos in one folder; camera poses need at least {MIN_PHOTOS} \
             overlapping views (20 or more around the subject work best)",
            found.map_or(0, |(_, n)| n)
        )),
    }
}

/// The video container a file starting with `head` is in (as a file extension), if any.
fn video_container(head: &[u8]) -> Option<&'static str> {
    match head {
        // ISO base media (MP4, MOV, M4V): a first box `ftyp` with the major brand.
        [_, _, _, _, b'f', b't', b'y', b'p', b'q', b't', b' ', b' ', ..] => Some("mov"),
        [_, _, _, _, b'f', b't', b'y', b'p', ..] => Some("mp4"),
        // Matroska and WebM (EBML).
        [0x1a, 0x45, 0xdf, 0xa3, ..] => Some("mkv"),
        [b'R', b'I', b'F', b'F', _, _, _, _, b'A', b'V', b'I', b' ', ..] => Some("avi"),
        // MPEG transport stream: sync bytes every 188 bytes, or every 192 with a time code.
        _ if head.len() > 376 && head[0] == 0x47 && head[188] == 0x47 && head[376] == 0x47 => {
            Some("mts")
        }
        _ if head.len() > 388 && head[4] == 0x47 && head[196] == 0x47 && head[388] == 0x47 => {
            Some("mts")
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stylenerf_testkit::{png, tar_of};

    fn check(bytes: &[u8]) -> Result<PhotosSummary, String> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("upload");
        std::fs::write(&path, bytes).unwrap();
        validate_photos(&path, &Limits::default())
    }

    #[test]
    fn a_folder_of_photos_or_a_video_is_accepted() {
        let photo = png(32, 24);
        let summary = check(&tar_of(&[
            ("trip/a.png", &photo),
            ("trip/b.PNG", &photo),
            ("trip/c.png", &photo),
            ("trip/notes.txt", b"x"),
            ("cover.png", &photo),
        ]))
        .unwrap();
        assert_eq!(
            (summary.source, summary.photos, summary.folder.as_str()),
            (Source::Photos, 3, "trip")
        );
        assert_eq!(summary.to_string(), "3 photos in trip/");
        let mp4 = [&[0, 0, 0, 0x20][..], b"ftypisom", &[0; 100]].concat();
        assert_eq!(check(&mp4).unwrap().extension, "mp4");
        let mov = [&[0, 0, 0, 0x14][..], b"ftypqt  ", &[0; 100]].concat();
        assert_eq!(check(&mov).unwrap().to_string(), "mov video");
        let webm = [&[0x1a, 0x45, 0xdf, 0xa3][..], &[0; 100]].concat();
        assert_eq!(check(&webm).unwrap().source, Source::Video);
    }

    #[test]
    fn too_few_unreadable_or_tiny_photos_are_refused_naming_the_member() {
        let photo = png(32, 24);
        let err = check(&tar_of(&[("a.png", &photo), ("b.jpg", &photo)])).unwrap_err();
        assert!(
            err.contains("2 PNG/JPEG photos") && err.contains("at least 3"),
            "{err}"
        );
        let err = check(&tar_of(&[("a.png", &photo), ("b.jpg", b"not a jpeg")])).unwrap_err();
        assert!(
            err.contains("\"b.jpg\"") && err.contains("not a readable"),
            "{err}"
        );
        let err = check(&tar_of(&[("a.png", &png(8, 8))])).unwrap_err();
        assert!(err.contains("too small"), "{err}");
        let err = check(b"GIF89a and more bytes than that").unwrap_err();
        assert!(
            err.contains("neither a tar archive of photos nor a video"),
            "{err}"
        );
    }
}
