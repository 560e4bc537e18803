//! Bad dataset input: every case gives an error naming the file, the field and the reason,
//! never a panic.

use std::path::{Path, PathBuf};

use serde_json::{json, Value};
use stylenerf_engine::scene::generate::{generate, CameraRig, GenerateOptions};
use stylenerf_engine::scene::npy::{self, Matrix};
use stylenerf_engine::scene::{LoadOptions, Scene, SceneFormat};
use tempfile::TempDir;

/// A small generated dataset: 8 views of 24×24 (frame 0 is test).
fn fixture(rig: CameraRig) -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    let opts = GenerateOptions {
        rig,
        size: 24,
        views: 8,
        seed: 3,
        ..GenerateOptions::default()
    };
    generate(&opts, dir.path()).unwrap();
    dir
}

fn transforms(dir: &Path) -> PathBuf {
    dir.join("transforms.json")
}

/// Applies `f` to transforms.json and writes it back.
fn edit(dir: &Path, f: impl FnOnce(&mut Value)) {
    let path = transforms(dir);
    let mut doc: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    f(&mut doc);
    std::fs::write(&path, serde_json::to_string_pretty(&doc).unwrap()).unwrap();
}

fn load(dir: &Path) -> String {
    load_with(dir, &LoadOptions::default())
}

fn load_with(path: &Path, opts: &LoadOptions) -> String {
    match Scene::load(path, opts) {
        Ok(_) => panic!("{} loaded but should not have", path.display()),
        Err(e) => e.to_string(),
    }
}

/// Asserts the message contains every part (file, field, reason).
fn assert_mentions(msg: &str, parts: &[&str]) {
    for part in parts {
        assert!(msg.contains(part), "`{part}` not in error: {msg}");
    }
}

#[test]
fn missing_image() {
    let d = fixture(CameraRig::Orbit);
    std::fs::remove_file(d.path().join("images/frame_00003.png")).unwrap();
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &["transforms.json", "frames[3].file_path", "does not exist"],
    );
}

#[test]
fn unreadable_image() {
    let d = fixture(CameraRig::Orbit);
    std::fs::write(d.path().join("images/frame_00002.png"), b"not a png").unwrap();
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &["transforms.json", "frames[2].file_path", "cannot decode"],
    );
}

#[test]
fn image_size_disagrees_with_intrinsics() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["w"] = json!(32));
    let msg = load(d.path());
    assert_mentions(&msg, &["transforms.json", "`w, h`", "24×24", "32×24"]);
}

#[test]
fn image_size_out_of_range_states_the_limit() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["w"] = json!(100000));
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &["transforms.json", "`w`", "from 1 to 16384", "100000"],
    );
}

#[test]
fn per_frame_size_override_is_named() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["frames"][4]["h"] = json!(20));
    let msg = load(d.path());
    assert_mentions(&msg, &["transforms.json", "frames[4].h", "24×20"]);
}

#[test]
fn transform_matrix_of_wrong_shape() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t["frames"][2]["transform_matrix"] = json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    });
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &["transforms.json", "frames[2].transform_matrix", "3×3"],
    );
}

#[test]
fn transform_matrix_that_is_not_a_rotation() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t["frames"][1]["transform_matrix"][0][0] = json!(3.0)
    });
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &[
            "transforms.json",
            "frames[1].transform_matrix",
            "not a rotation",
        ],
    );
}

/// Writes transforms.json with `value` (a bare token such as NaN) in place of `key`'s value.
fn edit_raw(dir: &Path, f: impl FnOnce(&mut Value), token: &str) {
    edit(dir, f);
    let path = transforms(dir);
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, text.replace("\"__TOKEN__\"", token)).unwrap();
}

#[test]
fn nan_in_pose() {
    let d = fixture(CameraRig::Orbit);
    edit_raw(
        d.path(),
        |t| t["frames"][1]["transform_matrix"][2][3] = json!("__TOKEN__"),
        "NaN",
    );
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &[
            "transforms.json",
            "frames[1].transform_matrix",
            "row 2, column 3",
            "non-finite",
        ],
    );
}

#[test]
fn infinity_in_intrinsics() {
    let d = fixture(CameraRig::Orbit);
    edit_raw(d.path(), |t| t["cx"] = json!("__TOKEN__"), "-Infinity");
    let msg = load(d.path());
    assert_mentions(&msg, &["transforms.json", "`cx`", "non-finite"]);
}

#[test]
fn non_positive_focal() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["fl_y"] = json!(-10.0));
    let msg = load(d.path());
    assert_mentions(&msg, &["transforms.json", "`fl_y`", "must be positive"]);
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["frames"][5]["fl_x"] = json!(0));
    let msg = load(d.path());
    assert_mentions(
        &msg,
        &["transforms.json", "frames[5].fl_x", "must be positive"],
    );
}

#[test]
fn missing_required_fields() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t["frames"][0].as_object_mut().unwrap().remove("file_path");
    });
    assert_mentions(
        &load(d.path()),
        &["transforms.json", "frames[0].file_path", "missing"],
    );

    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t.as_object_mut().unwrap().remove("h");
    });
    assert_mentions(&load(d.path()), &["transforms.json", "`h`", "missing"]);

    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t.as_object_mut().unwrap().remove("fl_x");
    });
    assert_mentions(&load(d.path()), &["transforms.json", "`fl_x`", "missing"]);

    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t.as_object_mut().unwrap().remove("frames");
    });
    assert_mentions(&load(d.path()), &["transforms.json", "`frames`", "missing"]);
}

#[test]
fn bad_json_reports_line_and_column() {
    let d = fixture(CameraRig::Orbit);
    std::fs::write(transforms(d.path()), "{\n  \"fl_x\": 10,\n  \"w\": ,\n}").unwrap();
    let msg = load(d.path());
    assert_mentions(&msg, &["transforms.json", "(syntax)", "line 3, column 8"]);
}

#[test]
fn wrong_types_are_named() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["frames"][3]["file_path"] = json!(7));
    assert_mentions(
        &load(d.path()),
        &[
            "transforms.json",
            "frames[3].file_path",
            "expected a string",
        ],
    );
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["aabb"] = json!([[1, 1, 1], [0, 0, 0]]));
    assert_mentions(&load(d.path()), &["transforms.json", "`aabb`", "below max"]);
}

#[test]
fn empty_splits() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t["train_filenames"] = json!([]);
        t["test_filenames"] = json!(["images/frame_00000.png"]);
    });
    assert_mentions(
        &load(d.path()),
        &["transforms.json", "`train_filenames`", "empty"],
    );

    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| {
        t["test_filenames"] = json!(["images/nope.png"])
    });
    assert_mentions(
        &load(d.path()),
        &[
            "transforms.json",
            "test_filenames[0]",
            "not the file_path of any frame",
        ],
    );

    let d = fixture(CameraRig::Orbit);
    let opts = LoadOptions {
        max_frames: Some(1),
        ..LoadOptions::default()
    };
    assert_mentions(
        &load_with(d.path(), &opts),
        &["transforms.json", "`frames`", "training split is empty"],
    );
}

#[test]
fn paths_escaping_the_dataset_folder() {
    let outer = tempfile::tempdir().unwrap();
    let root = outer.path().join("data");
    generate(
        &GenerateOptions {
            size: 24,
            views: 8,
            seed: 3,
            ..GenerateOptions::default()
        },
        &root,
    )
    .unwrap();
    // The escaping targets exist, so only the containment check can reject them.
    std::fs::copy(
        root.join("images/frame_00001.png"),
        outer.path().join("outside.png"),
    )
    .unwrap();

    edit(&root, |t| {
        t["frames"][1]["file_path"] = json!("../outside.png")
    });
    assert_mentions(
        &load(&root),
        &[
            "transforms.json",
            "frames[1].file_path",
            "outside the dataset folder",
        ],
    );

    let absolute = outer.path().join("outside.png");
    edit(&root, |t| {
        t["frames"][1]["file_path"] = json!(absolute.to_str().unwrap())
    });
    assert_mentions(
        &load(&root),
        &[
            "transforms.json",
            "frames[1].file_path",
            "outside the dataset folder",
        ],
    );

    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(&absolute, root.join("images/link.png")).unwrap();
        edit(&root, |t| {
            t["frames"][1]["file_path"] = json!("images/link.png")
        });
        assert_mentions(
            &load(&root),
            &["transforms.json", "frames[1].file_path", "symbolic link"],
        );
        edit(&root, |t| {
            t["frames"][1]["file_path"] = json!("images/frame_00001.png");
            t["frames"][1]["depth_file_path"] = json!("images/link.png");
        });
        assert_mentions(
            &load(&root),
            &[
                "transforms.json",
                "frames[1].depth_file_path",
                "symbolic link",
            ],
        );
    }

    // An absolute path inside the folder is fine.
    let inside = root.canonicalize().unwrap().join("images/frame_00001.png");
    edit(&root, |t| {
        t["frames"][1]["file_path"] = json!(inside.to_str().unwrap());
        t["frames"][1]["depth_file_path"] = json!("depths/frame_00001.png");
    });
    Scene::load(&root, &LoadOptions::default()).unwrap();
}

#[test]
fn unsupported_camera_models_and_distortion() {
    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["camera_model"] = json!("OPENCV_FISHEYE"));
    assert_mentions(
        &load(d.path()),
        &[
            "transforms.json",
            "`camera_model`",
            "unsupported camera model",
        ],
    );

    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["frames"][2]["p1"] = json!(0.01));
    assert_mentions(
        &load(d.path()),
        &[
            "transforms.json",
            "frames[2].p1",
            "set camera_model to OPENCV",
        ],
    );
}

#[test]
fn depth_map_problems() {
    let d = fixture(CameraRig::Orbit);
    std::fs::copy(
        d.path().join("images/frame_00000.png"),
        d.path().join("depths/frame_00006.png"),
    )
    .unwrap();
    assert_mentions(
        &load(d.path()),
        &[
            "transforms.json",
            "frames[6].depth_file_path",
            "16-bit grayscale",
        ],
    );

    let d = fixture(CameraRig::Orbit);
    let small = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(12, 12);
    small.save(d.path().join("depths/frame_00006.png")).unwrap();
    assert_mentions(
        &load(d.path()),
        &["transforms.json", "frames[6].depth_file_path", "12×12"],
    );

    let d = fixture(CameraRig::Orbit);
    edit(d.path(), |t| t["depth_unit_scale_factor"] = json!(0));
    assert_mentions(
        &load(d.path()),
        &["transforms.json", "depth_unit_scale_factor", "positive"],
    );
}

#[test]
fn bad_options_are_config_errors() {
    let d = fixture(CameraRig::Orbit);
    let opts = LoadOptions {
        downscale: 0,
        ..LoadOptions::default()
    };
    assert_mentions(&load_with(d.path(), &opts), &["downscale", "at least 1"]);
    let msg = Scene::load(d.path().join("nothing-here"), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert_mentions(&msg, &["nothing-here", "no such file or folder"]);
}

fn poses_bounds(dir: &Path) -> PathBuf {
    dir.join("poses_bounds.npy")
}

fn llff() -> LoadOptions {
    LoadOptions {
        format: Some(SceneFormat::Llff),
        ..LoadOptions::default()
    }
}

#[test]
fn llff_wrong_shape() {
    let d = fixture(CameraRig::Forward);
    let m = npy::read_matrix(&poses_bounds(d.path())).unwrap();
    let narrow = Matrix {
        rows: m.rows,
        cols: 15,
        data: (0..m.rows).flat_map(|r| m.row(r)[..15].to_vec()).collect(),
    };
    npy::write_matrix(&poses_bounds(d.path()), &narrow).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &["poses_bounds.npy", "`shape`", "N×17", "8×15"],
    );
}

#[test]
fn llff_non_finite_values() {
    let d = fixture(CameraRig::Forward);
    let mut m = npy::read_matrix(&poses_bounds(d.path())).unwrap();
    let original = m.clone();
    m.data[3 * 17 + 7] = f64::NAN;
    npy::write_matrix(&poses_bounds(d.path()), &m).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &["poses_bounds.npy", "row 3 (values)", "column 7 is NaN"],
    );

    let mut m = original;
    m.data[5 * 17 + 14] = -1.0;
    npy::write_matrix(&poses_bounds(d.path()), &m).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &[
            "poses_bounds.npy",
            "row 5 (height, width, focal)",
            "positive",
        ],
    );
}

#[test]
fn llff_image_count_and_size() {
    let d = fixture(CameraRig::Forward);
    std::fs::remove_file(d.path().join("images/frame_00007.png")).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &["poses_bounds.npy", "`shape`", "8 poses but 7 images"],
    );

    let d = fixture(CameraRig::Forward);
    let mut m = npy::read_matrix(&poses_bounds(d.path())).unwrap();
    m.data[2 * 17 + 9] = 30.0; // width of row 2
    npy::write_matrix(&poses_bounds(d.path()), &m).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &[
            "poses_bounds.npy",
            "row 2 (height, width)",
            "24×24",
            "30×24",
        ],
    );
}

#[test]
fn llff_bad_npy_files() {
    let d = fixture(CameraRig::Forward);
    let path = poses_bounds(d.path());
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() - 8]).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &["poses_bounds.npy", "`data`", "bytes"],
    );

    let mut patched = bytes.clone();
    let at = bytes.windows(3).position(|w| w == b"<f8").unwrap();
    patched[at..at + 3].copy_from_slice(b"<i8");
    std::fs::write(&path, patched).unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &["poses_bounds.npy", "`descr`", "<i8"],
    );

    std::fs::write(&path, b"hello").unwrap();
    assert_mentions(
        &load_with(d.path(), &llff()),
        &["poses_bounds.npy", "`header`", "magic"],
    );
}

#[test]
fn blender_problems() {
    const POSE: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]";
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("transforms_train.json"),
        format!(r#"{{"frames": [{{"file_path": "./train/r_0", "transform_matrix": {POSE}}}]}}"#),
    )
    .unwrap();
    assert_mentions(
        &load(d.path()),
        &["transforms_train.json", "`camera_angle_x`", "missing"],
    );

    std::fs::write(
        d.path().join("transforms_train.json"),
        format!(
            r#"{{"camera_angle_x": 0.7,
                "frames": [{{"file_path": "./train/r_0", "transform_matrix": {POSE}}}]}}"#
        ),
    )
    .unwrap();
    assert_mentions(
        &load(d.path()),
        &[
            "transforms_train.json",
            "frames[0].file_path",
            "train/r_0.png",
            "does not exist",
        ],
    );
}
