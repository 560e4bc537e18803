//! Property tests of the engine's parsers of user data: whatever a `transforms.json`, an
//! `.npy` file or a job's overrides hold, loading gives a value or an error naming the file
//! or key — never a panic. Each property runs proptest's `PROPTEST_CASES` cases (256 unless
//! set; the longer run in docs/BENCHMARKS.md sets 5000).

use std::path::Path;

use proptest::prelude::*;
use serde_json::{json, Value};
use stylenerf_engine::scene::generate::{generate, GenerateOptions};
use stylenerf_engine::scene::npy;
use stylenerf_engine::scene::{LoadOptions, Scene};
use stylenerf_engine::stages::dispatch::check_job_overrides;

/// Any JSON value, a few levels deep, with the numbers and strings that break parsers.
fn any_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::from),
        any::<i64>().prop_map(Value::from),
        any::<f64>()
            .prop_filter("JSON has no NaN", |x| x.is_finite())
            .prop_map(Value::from),
        prop_oneof![Just(0.0), Just(-1.0), Just(1e300), Just(-1e-300), Just(1e9)]
            .prop_map(Value::from),
        "\\PC{0,12}".prop_map(Value::from),
        prop_oneof![
            Just("../../etc/passwd"),
            Just("/abs.png"),
            Just(""),
            Just("a\\b")
        ]
        .prop_map(Value::from),
    ];
    leaf.prop_recursive(3, 24, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,8}", inner, 0..4)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

/// Where a mutation lands in a nerfstudio document.
fn any_place() -> impl Strategy<Value = (Option<usize>, String)> {
    let keys = prop_oneof![
        Just("fl_x"),
        Just("fl_y"),
        Just("cx"),
        Just("cy"),
        Just("w"),
        Just("h"),
        Just("camera_model"),
        Just("k1"),
        Just("p1"),
        Just("aabb_scale"),
        Just("aabb"),
        Just("near"),
        Just("far"),
        Just("background"),
        Just("frames"),
        Just("file_path"),
        Just("transform_matrix"),
        Just("depth_file_path"),
        Just("mask_path"),
        Just("depth_unit_scale_factor"),
    ];
    (prop::option::of(0usize..8), keys.prop_map(String::from))
}

fn scene_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    generate(
        &GenerateOptions {
            size: 16,
            views: 4,
            ..GenerateOptions::default()
        },
        dir.path(),
    )
    .unwrap();
    dir
}

/// Sets `key` of the document or of one of its frames (when `frames` is still a list).
fn mutate(doc: &mut Value, frame: Option<usize>, key: &str, value: Value) {
    let target = match frame {
        Some(i) => match doc["frames"].as_array_mut() {
            Some(frames) if !frames.is_empty() => {
                let n = frames.len();
                &mut frames[i % n]
            }
            _ => return,
        },
        None => doc,
    };
    if let Some(object) = target.as_object_mut() {
        object.insert(key.to_string(), value);
    }
}

fn check_error_names_the_file(result: stylenerf_engine::Result<Scene>, dir: &Path) {
    if let Err(e) = result {
        let message = e.to_string();
        assert!(
            message.contains(&dir.display().to_string()) || message.contains("transforms.json"),
            "{message}"
        );
    }
}

#[test]
fn transforms_json_never_panics_the_loader() {
    let dir = scene_dir();
    let path = dir.path().join("transforms.json");
    let original: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let options = LoadOptions {
        max_side: Some(8),
        ..LoadOptions::default()
    };
    proptest!(|(mutations in prop::collection::vec((any_place(), any_json()), 1..4))| {
        let mut doc = original.clone();
        for ((frame, key), value) in mutations {
            mutate(&mut doc, frame, &key, value);
        }
        std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
        check_error_names_the_file(Scene::load(dir.path(), &options), dir.path());
    });
}

#[test]
fn any_bytes_as_transforms_json_or_npy_give_an_error_not_a_panic() {
    let dir = scene_dir();
    let path = dir.path().join("transforms.json");
    let npy_path = dir.path().join("depth.npy");
    let valid_npy = {
        let matrix = npy::Matrix {
            rows: 2,
            cols: 3,
            data: vec![1.0; 6],
        };
        npy::write_matrix(&npy_path, &matrix).unwrap();
        std::fs::read(&npy_path).unwrap()
    };
    proptest!(|(bytes in prop::collection::vec(any::<u8>(), 0..512),
                          flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..6),
                          cut in any::<prop::sample::Index>())| {
        std::fs::write(&path, &bytes).unwrap();
        check_error_names_the_file(Scene::load(dir.path(), &LoadOptions::default()), dir.path());
        // Random bytes, and a valid file with bytes changed and cut short.
        std::fs::write(&npy_path, &bytes).unwrap();
        let _ = npy::read_matrix(&npy_path);
        let mut damaged = valid_npy.clone();
        for (at, byte) in flips {
            let i = at.index(damaged.len());
            damaged[i] = byte;
        }
        damaged.truncate(cut.index(damaged.len() + 1));
        std::fs::write(&npy_path, &damaged).unwrap();
        if let Err(e) = npy::read_matrix(&npy_path) {
            prop_assert!(e.to_string().contains("depth.npy"), "{}", e);
        }
    });
}

#[test]
fn any_overrides_are_checked_without_panicking() {
    let keys = prop_oneof![
        Just("nerf_pretrain.steps"),
        Just("nerf_pretrain.rays_per_batch"),
        Just("nerf_pretrain.field.grid.levels"),
        Just("nerf_pretrain.field.grid.log2_table_size"),
        Just("nerf_pretrain.field"),
        Just("render_views.chunk"),
        Just("decoder_pretrain.patch"),
        Just("mutual_learning.style_module"),
        Just("render_stylized.styles"),
        Just("steps"),
        Just("nerf_pretrain"),
        Just("x.y.z"),
    ];
    proptest!(|(overrides in prop::collection::vec((keys, any_json()), 0..5),
                          preset in prop_oneof![Just("tiny"), Just("quick"), Just("paper"), Just("nope")])| {
        let map: serde_json::Map<String, Value> =
            overrides.into_iter().map(|(k, v)| (k.to_string(), v)).collect();
        let problems = check_job_overrides(preset, &map);
        for (key, reason) in &problems {
            prop_assert!(!key.is_empty() && !reason.is_empty());
        }
        if preset != "nope" && map.is_empty() {
            prop_assert!(problems.is_empty());
        }
    });
    // A known good set stays good.
    let good = json!({"nerf_pretrain": {"steps": 10, "field": {"grid": {"levels": 4}}}});
    assert_eq!(
        check_job_overrides("tiny", good.as_object().unwrap()),
        Vec::<(String, String)>::new()
    );
}
