//! The dataset formats and the one rule for finding a scene in an upload, shared by the
//! coordinator (which sees archive member paths), the worker (which sees the unpacked folder)
//! and the engine's loaders (which name the same marker files); and the same for the photos of
//! an upload of plain photos ([`find_photos`]); and what the coordinator keeps of a loaded
//! dataset for the submission checks that depend on it ([`DatasetFacts`]).

use serde::{Deserialize, Serialize};

/// A dataset format, known by the file that marks a folder as holding it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneFormat {
    /// nerfstudio / instant-ngp `transforms.json`.
    Nerfstudio,
    /// NeRF-synthetic `transforms_{train,val,test}.json`.
    Blender,
    /// LLFF `poses_bounds.npy` + `images/` (forward-facing, NDC rays).
    Llff,
}

/// What the engine's loader found in a dataset that settings depend on: recorded with the
/// upload, so that a job asking for what the dataset lacks is refused at submission.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DatasetFacts {
    /// Some training frame has a depth map (what `nerf_pretrain.depth_weight` trains on).
    pub train_depth: bool,
}

/// Deepest folder, counted from the upload's root, that a scene is looked for in.
pub const MAX_SCENE_DEPTH: usize = 2;

/// What to say when an upload holds no scene.
pub const NO_SCENE: &str = "no scene file: expected transforms.json (nerfstudio), \
     transforms_train.json (Blender) or poses_bounds.npy (LLFF) at the root or in a folder \
     (two levels down at most)";

impl SceneFormat {
    /// Every format, in the order a folder holding several is read.
    pub const ALL: [SceneFormat; 3] = [Self::Nerfstudio, Self::Blender, Self::Llff];

    pub const fn name(self) -> &'static str {
        match self {
            Self::Nerfstudio => "nerfstudio",
            Self::Blender => "blender",
            Self::Llff => "llff",
        }
    }

    /// The file that marks a folder as holding this format.
    pub const fn marker(self) -> &'static str {
        match self {
            Self::Nerfstudio => "transforms.json",
            Self::Blender => "transforms_train.json",
            Self::Llff => "poses_bounds.npy",
        }
    }

    /// The format whose marker is named `file_name`.
    pub fn of_marker(file_name: &str) -> Option<SceneFormat> {
        Self::ALL.into_iter().find(|f| f.marker() == file_name)
    }
}

impl std::fmt::Display for SceneFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The scene among the `/`-separated relative `files` of an upload: its marker in the
/// shallowest folder (at most [`MAX_SCENE_DEPTH`] below the root) that holds one, the first
/// such folder by name, and in it the first format of [`SceneFormat::ALL`]. Returns the format
/// and the marker's path.
pub fn find_scene<'a>(files: impl IntoIterator<Item = &'a str>) -> Option<(SceneFormat, &'a str)> {
    files
        .into_iter()
        .filter_map(|path| {
            let (dir, name) = path.rsplit_once('/').unwrap_or(("", path));
            let format = SceneFormat::of_marker(name)?;
            let depth = path.matches('/').count();
            let order = SceneFormat::ALL.iter().position(|f| *f == format);
            (depth <= MAX_SCENE_DEPTH).then_some(((depth, dir, order), (format, path)))
        })
        .min_by(|a, b| a.0.cmp(&b.0))
        .map(|(_, found)| found)
}

/// Extensions (lower case) of the photos COLMAP and the loaders read.
pub const PHOTO_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Fewest photos camera poses can be recovered from.
pub const MIN_PHOTOS: usize = 3;

/// The folder of an upload of plain photos that holds them, among its `/`-separated relative
/// `files`: the folder (at most [`MAX_SCENE_DEPTH`] below the root) with the most photos, the
/// shallowest and then the first by name among equals. Returns the folder (`""` for the root)
/// and its number of photos.
pub fn find_photos<'a>(files: impl IntoIterator<Item = &'a str>) -> Option<(&'a str, usize)> {
    let mut counts: std::collections::BTreeMap<&str, usize> = Default::default();
    for path in files {
        let (dir, name) = path.rsplit_once('/').unwrap_or(("", path));
        let photo = name.rsplit_once('.').is_some_and(|(stem, ext)| {
            !stem.is_empty() && PHOTO_EXTENSIONS.contains(&ext.to_ascii_lowercase().as_str())
        });
        if photo && path.matches('/').count() <= MAX_SCENE_DEPTH {
            *counts.entry(dir).or_default() += 1;
        }
    }
    counts
        .into_iter()
        .min_by_key(|&(dir, n)| (std::cmp::Reverse(n), dir.matches('/').count(), dir))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shallowest_first_folder_and_first_format_win() {
        let found = |files: &[&'static str]| find_scene(files.iter().copied());
        assert_eq!(
            found(&[
                "b/transforms.json",
                "a/x/transforms.json",
                "a/poses_bounds.npy"
            ]),
            Some((SceneFormat::Llff, "a/poses_bounds.npy"))
        );
        assert_eq!(
            found(&[
                "s/poses_bounds.npy",
                "s/transforms_train.json",
                "s/images/a.png"
            ]),
            Some((SceneFormat::Blender, "s/transforms_train.json"))
        );
        assert_eq!(
            found(&["transforms.json", "a/transforms_train.json"]),
            Some((SceneFormat::Nerfstudio, "transforms.json"))
        );
        assert_eq!(found(&["a/b/c/transforms.json", "x.png"]), None);
        assert_eq!(
            SceneFormat::of_marker("poses_bounds.npy"),
            Some(SceneFormat::Llff)
        );
        assert_eq!(
            serde_json::to_value(SceneFormat::Blender).unwrap(),
            serde_json::json!("blender")
        );
    }

    #[test]
    fn the_folder_with_the_most_photos_holds_them() {
        let found = |files: &[&'static str]| find_photos(files.iter().copied());
        assert_eq!(
            found(&[
                "a.png",
                "p/1.JPG",
                "p/2.jpeg",
                "q/x.png",
                "p/notes.txt",
                "p/.png"
            ]),
            Some(("p", 2))
        );
        assert_eq!(found(&["b/1.png", "a/1.png"]), Some(("a", 1)));
        assert_eq!(found(&["1.png", "a/1.png"]), Some(("", 1)));
        assert_eq!(found(&["a/b/c/1.png", "readme.md"]), None);
    }
}
