//! Loading good datasets of every format (generated ones and a hand-written Blender one), and
//! the generator's determinism and ground-truth depth.

use std::path::Path;

use glam::Vec3;
use image::{Rgba, RgbaImage};
use serde_json::{json, Value};
use stylenerf_engine::camera::Camera;
use stylenerf_engine::scene::generate::{generate, CameraRig, GenerateOptions, Surroundings};
use stylenerf_engine::scene::{Background, LoadOptions, Scene, SceneFormat};
use tempfile::TempDir;

fn fixture(rig: CameraRig, size: u32, views: usize) -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    let opts = GenerateOptions {
        rig,
        size,
        views,
        seed: 11,
        ..GenerateOptions::default()
    };
    generate(&opts, dir.path()).unwrap();
    dir
}

fn edit(dir: &Path, f: impl FnOnce(&mut Value)) {
    let path = dir.join("transforms.json");
    let mut doc: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    f(&mut doc);
    std::fs::write(&path, serde_json::to_string_pretty(&doc).unwrap()).unwrap();
}

fn depth_at(camera: &Camera, depth: &[f32], x: u32, y: u32) -> f32 {
    depth[(y * camera.intrinsics.width + x) as usize]
}

#[test]
fn orbit_scene_loads_as_nerfstudio() {
    let d = fixture(CameraRig::Orbit, 32, 12);
    let (format, _) = stylenerf_engine::scene::detect(d.path()).unwrap();
    assert_eq!(format, SceneFormat::Nerfstudio);
    let scene = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    assert_eq!(scene.frames.len(), 12);
    assert_eq!(scene.test, vec![0, 8]);
    assert_eq!(scene.train.len(), 10);
    assert_eq!(scene.resolution(), (32, 32));
    assert_eq!(scene.aabb.min, Vec3::splat(-1.0));
    assert!(scene.ndc.is_none() && scene.near > 0.0 && scene.far > scene.near);
    assert_eq!(scene.background, Background::Colour([0.8, 0.86, 0.93]));
    let frame = &scene.frames[3];
    assert_eq!(frame.name, "images/frame_00003.png");
    let png = image::open(d.path().join(&frame.name)).unwrap().to_rgb8();
    let (px, loaded) = (png.get_pixel(5, 7).0, frame.image.get_pixel(5, 7).0);
    for c in 0..3 {
        assert!((px[c] as f32 / 255.0 - loaded[c]).abs() < 1e-6);
    }
    assert!(scene
        .frames
        .iter()
        .all(|f| f.depth.as_ref().is_some_and(|d| d.len() == 32 * 32)));
}

#[test]
fn downscale_max_frames_and_explicit_splits() {
    let d = fixture(CameraRig::Orbit, 32, 12);
    let full = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    let opts = LoadOptions {
        downscale: 2,
        max_frames: Some(5),
        ..LoadOptions::default()
    };
    let small = Scene::load(d.path().join("transforms.json"), &opts).unwrap();
    assert_eq!(small.frames.len(), 5);
    assert_eq!((small.train.len(), small.test.len()), (4, 1));
    assert_eq!(small.resolution(), (16, 16));
    let (k, k_full) = (
        small.frames[0].camera.intrinsics,
        full.frames[0].camera.intrinsics,
    );
    assert!((k.fx * 2.0 - k_full.fx).abs() < 1e-4 && (k.cx * 2.0 - k_full.cx).abs() < 1e-4);
    assert_eq!(small.frames[0].depth.as_ref().unwrap().len(), 16 * 16);

    edit(d.path(), |t| {
        t["train_filenames"] = json!(["images/frame_00001.png", "./images/frame_00002.png"]);
        t["test_filenames"] = json!(["images/frame_00005.png"]);
    });
    let s = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    let names: Vec<&str> = s.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "images/frame_00001.png",
            "images/frame_00002.png",
            "images/frame_00005.png"
        ]
    );
    assert_eq!((s.train.clone(), s.test.clone()), (vec![0, 1], vec![2]));
}

#[test]
fn bounds_are_estimated_when_absent() {
    let d = fixture(CameraRig::Orbit, 16, 12);
    edit(d.path(), |t| {
        let t = t.as_object_mut().unwrap();
        for key in ["aabb", "near", "far", "background"] {
            t.remove(key);
        }
    });
    let s = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    // The cameras look at (0, -0.3, 0) from 2.7 away.
    assert!(
        (s.aabb.center() - Vec3::new(0.0, -0.3, 0.0)).length() < 1e-2,
        "{:?}",
        s.aabb
    );
    assert!((s.aabb.size().x - 5.4).abs() < 1e-2);
    // Photos without alpha, without a stated box or background: a real capture.
    assert!(s.near > 0.0 && s.far > 2.7 && s.background == Background::Learned && s.unbounded);
}

#[test]
fn forward_scene_loads_as_llff_with_ndc() {
    let d = fixture(CameraRig::Forward, 32, 16);
    let opts = LoadOptions {
        format: Some(SceneFormat::Llff),
        ..LoadOptions::default()
    };
    let llff = Scene::load(d.path(), &opts).unwrap();
    let ns = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    assert_eq!(llff.frames.len(), 16);
    assert_eq!(llff.test, vec![0, 8]);
    assert_eq!((llff.near, llff.far), (0.0, 1.0));
    assert_eq!((llff.aabb.min.z, llff.aabb.max.z), (-1.0, 1.0));
    assert!(llff.aabb.min.cmple(Vec3::NEG_ONE).all() && llff.aabb.max.cmpge(Vec3::ONE).all());
    let ndc = llff.ndc.expect("LLFF scenes use NDC");
    assert_eq!((ndc.width, ndc.height, ndc.near), (32, 32, 1.0));

    // The LLFF poses are the world poses up to one similarity: relative rotations agree and
    // distances scale by one factor.
    let (a, b) = (&llff.frames, &ns.frames);
    let scale = (a[5].camera.position - a[0].camera.position).length()
        / (b[5].camera.position - b[0].camera.position).length();
    for (i, j) in [(1, 2), (3, 12), (0, 15)] {
        let ratio = (a[i].camera.position - a[j].camera.position).length()
            / (b[i].camera.position - b[j].camera.position).length();
        assert!((ratio - scale).abs() < 1e-3 * scale, "{ratio} vs {scale}");
        let rel_a = a[i].camera.rotation.transpose() * a[j].camera.rotation;
        let rel_b = b[i].camera.rotation.transpose() * b[j].camera.rotation;
        assert!(rel_a.abs_diff_eq(rel_b, 1e-4));
    }
    // Every surface point lies beyond the NDC near plane of the re-centred frame, and inside
    // the scene's NDC box.
    let (cam_w, cam_l) = (&b[4].camera, &a[4].camera);
    let depth = b[4].depth.as_ref().unwrap();
    for y in 0..32 {
        for x in 0..32 {
            let z = depth_at(cam_w, depth, x, y);
            if z > 0.0 {
                let p = cam_l.unproject(x as f32 + 0.5, y as f32 + 0.5, z * scale);
                assert!(p.z < -ndc.near, "{p}");
                let ray = cam_l.pixel_ray(x, y);
                let (o, dir) = ndc.ray(&ray);
                let t_ndc = (1.0 + 2.0 * ndc.near / p.z - o.z) / dir.z;
                assert!((0.0..=1.0).contains(&t_ndc));
                let q = o + t_ndc * dir;
                let box_ = llff.aabb;
                assert!(
                    box_.min.cmple(q + 1e-4).all() && box_.max.cmpge(q - 1e-4).all(),
                    "{q}"
                );
            }
        }
    }
    // Downscaling by 2 without an images_2/ folder resizes.
    let half = Scene::load(
        d.path(),
        &LoadOptions {
            downscale: 2,
            ..opts
        },
    )
    .unwrap();
    assert_eq!(half.resolution(), (16, 16));
    assert_eq!(half.ndc.unwrap().width, 16);
}

#[test]
fn llff_prefers_a_minified_folder() {
    let d = fixture(CameraRig::Forward, 32, 8);
    let minified = d.path().join("images_4");
    std::fs::create_dir(&minified).unwrap();
    for i in 0..8 {
        let name = format!("frame_{i:05}.png");
        image::open(d.path().join("images").join(&name))
            .unwrap()
            .resize_exact(8, 8, image::imageops::FilterType::Triangle)
            .save(minified.join(&name))
            .unwrap();
    }
    let opts = LoadOptions {
        format: Some(SceneFormat::Llff),
        downscale: 4,
        ..LoadOptions::default()
    };
    let s = Scene::load(d.path(), &opts).unwrap();
    assert_eq!(s.resolution(), (8, 8));
    assert_eq!(s.frames[0].name, "images_4/frame_00000.png");
}

/// Writes a 2+1-frame NeRF-synthetic dataset with 8×8 RGBA images: left half transparent.
fn blender_fixture(dir: &Path) {
    for split in ["train", "test"] {
        std::fs::create_dir_all(dir.join(split)).unwrap();
    }
    let img = RgbaImage::from_fn(8, 8, |x, _| {
        if x < 4 {
            Rgba([0, 0, 0, 0])
        } else {
            Rgba([255, 0, 0, 255])
        }
    });
    let frames = |split: &str, n: usize| -> Value {
        (0..n)
            .map(|i| {
                img.save(dir.join(format!("{split}/r_{i}.png"))).unwrap();
                let z = 4.0 + i as f32;
                json!({
                    "file_path": format!("./{split}/r_{i}"),
                    "rotation": 0.012,
                    "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, z], [0, 0, 0, 1]],
                })
            })
            .collect()
    };
    for (split, n) in [("train", 2), ("test", 1)] {
        let doc = json!({"camera_angle_x": 0.6911112070083618, "frames": frames(split, n)});
        std::fs::write(
            dir.join(format!("transforms_{split}.json")),
            doc.to_string(),
        )
        .unwrap();
    }
}

#[test]
fn blender_scene_composites_alpha() {
    let d = tempfile::tempdir().unwrap();
    blender_fixture(d.path());
    let s = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    assert_eq!((s.train.clone(), s.test.clone()), (vec![0, 1], vec![2]));
    assert_eq!((s.near, s.far, s.aabb.max), (2.0, 6.0, Vec3::splat(1.5)));
    let f = &s.frames[0];
    assert_eq!(f.name, "./train/r_0.png");
    let k = f.camera.intrinsics;
    assert!((k.fx - 4.0 / (0.6911112f32 / 2.0).tan()).abs() < 1e-4 && k.cx == 4.0);
    assert_eq!(f.image.get_pixel(1, 1).0, [1.0, 1.0, 1.0]);
    assert_eq!(f.image.get_pixel(6, 1).0, [1.0, 0.0, 0.0]);
    assert_eq!(s.frames[2].camera.position, Vec3::new(0.0, 0.0, 4.0));

    let opts = LoadOptions {
        background: Some([0.0, 0.5, 0.0]),
        ..LoadOptions::default()
    };
    let s = Scene::load(d.path().join("transforms_train.json"), &opts).unwrap();
    assert_eq!(s.frames[0].image.get_pixel(1, 1).0, [0.0, 0.5, 0.0]);
    assert_eq!(s.background, Background::Colour([0.0, 0.5, 0.0]));
}

/// Moves each pixel of an ideal image to where a lens with `k1, k2, p1, p2` records it:
/// the recorded pixel at distorted coordinates shows the ideal image at the undistorted ones
/// (found by fixed-point iteration).
fn distort_image(ideal: &image::RgbImage, f: f32, c: f32, k: [f32; 4]) -> image::RgbImage {
    let [k1, k2, p1, p2] = k;
    let (w, h) = ideal.dimensions();
    image::RgbImage::from_fn(w, h, |u, v| {
        let (xd, yd) = ((u as f32 + 0.5 - c) / f, (v as f32 + 0.5 - c) / f);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            x = (xd - dx) / radial;
            y = (yd - dy) / radial;
        }
        let (su, sv) = ((x * f + c) / w as f32, (y * f + c) / h as f32);
        image::imageops::sample_bilinear(ideal, su, sv).unwrap_or(image::Rgb([0, 0, 0]))
    })
}

#[test]
fn opencv_distortion_is_undistorted() {
    let d = fixture(CameraRig::Orbit, 128, 8);
    let ideal = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    let doc: Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("transforms.json")).unwrap())
            .unwrap();
    let (f, c) = (
        doc["fl_x"].as_f64().unwrap() as f32,
        doc["cx"].as_f64().unwrap() as f32,
    );
    let coeffs = [-0.45, 0.1, 0.004, -0.003];
    for i in 0..8 {
        let path = d.path().join(format!("images/frame_{i:05}.png"));
        let img = image::open(&path).unwrap().to_rgb8();
        distort_image(&img, f, c, coeffs).save(&path).unwrap();
    }
    let raw = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    edit(d.path(), |t| {
        t["camera_model"] = json!("OPENCV");
        for (key, v) in ["k1", "k2", "p1", "p2"].iter().zip(coeffs) {
            t[*key] = json!(v);
        }
    });
    let fixed = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    // Mean error against the ideal images over the central region.
    let err = |s: &Scene| {
        let mut sum = 0.0;
        let mut n = 0;
        for (a, b) in s.frames.iter().zip(&ideal.frames) {
            for y in 16..112 {
                for x in 16..112 {
                    let (p, q) = (a.image.get_pixel(x, y).0, b.image.get_pixel(x, y).0);
                    sum += (0..3).map(|c| (p[c] - q[c]).abs()).sum::<f32>();
                    n += 3;
                }
            }
        }
        sum / n as f32
    };
    let (before, after) = (err(&raw), err(&fixed));
    assert!(
        after < 0.5 * before && after < 0.03,
        "distorted {before}, undistorted {after}"
    );
}

#[test]
fn generator_is_deterministic() {
    let opts = GenerateOptions {
        size: 24,
        views: 4,
        ..GenerateOptions::default()
    };
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    generate(&opts, a.path()).unwrap();
    generate(&opts, b.path()).unwrap();
    for file in [
        "transforms.json",
        "images/frame_00002.png",
        "depths/frame_00003.png",
    ] {
        let (x, y) = (
            std::fs::read(a.path().join(file)).unwrap(),
            std::fs::read(b.path().join(file)).unwrap(),
        );
        assert!(x == y, "{file} differs between runs");
    }
    let c = tempfile::tempdir().unwrap();
    generate(
        &GenerateOptions {
            seed: 8,
            ..opts.clone()
        },
        c.path(),
    )
    .unwrap();
    let image = "images/frame_00002.png";
    assert_ne!(
        std::fs::read(a.path().join(image)).unwrap(),
        std::fs::read(c.path().join(image)).unwrap()
    );
    // A non-empty output folder is refused rather than mixed with.
    let msg = generate(&opts, a.path()).unwrap_err().to_string();
    assert!(msg.contains("not empty"), "{msg}");
}

/// Ground-truth depth agrees with the cameras: surface points seen in one view, moved into a
/// neighbouring view, land at the depth that view recorded around there, or behind something
/// nearer (occluded); never in front of what that view saw (which would mean seeing through a
/// surface). Every surface point lies inside the scene box.
#[test]
fn ground_truth_depth_is_consistent_across_views() {
    let size = 64;
    let d = fixture(CameraRig::Orbit, size, 24);
    let s = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    let (mut checked, mut agree, mut see_through) = (0, 0, 0);
    for i in 0..s.frames.len() - 1 {
        let (a, b) = (&s.frames[i], &s.frames[i + 1]);
        let (da, db) = (a.depth.as_ref().unwrap(), b.depth.as_ref().unwrap());
        for y in 0..size {
            for x in 0..size {
                let z = depth_at(&a.camera, da, x, y);
                if z == 0.0 {
                    continue;
                }
                let p = a.camera.unproject(x as f32 + 0.5, y as f32 + 0.5, z);
                assert!(
                    s.aabb.min.cmple(p + 1e-3).all() && s.aabb.max.cmpge(p - 1e-3).all(),
                    "{p}"
                );
                let (u, v, zb) = b.camera.project(p);
                let inside = |c: f32| (0.5..size as f32 - 0.5).contains(&c);
                if !(inside(u) && inside(v)) {
                    continue;
                }
                // The four pixel centres around the projection; 0 (background) counts as far.
                let (x0, y0) = ((u - 0.5) as u32, (v - 0.5) as u32);
                let seen: Vec<f32> = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|&(dx, dy)| depth_at(&b.camera, db, x0 + dx, y0 + dy))
                    .map(|d| if d == 0.0 { f32::INFINITY } else { d })
                    .collect();
                checked += 1;
                if seen.iter().any(|d| (d - zb).abs() < 0.01 * zb) {
                    agree += 1;
                } else if seen.iter().all(|&d| d > zb) {
                    see_through += 1;
                }
            }
        }
    }
    let (agree, see_through) = (
        agree as f32 / checked as f32,
        see_through as f32 / checked as f32,
    );
    assert!(checked > 30_000, "{checked}");
    assert!(
        agree > 0.6 && see_through < 0.005,
        "agree {agree}, see-through {see_through}"
    );
}

fn surrounded(surroundings: Surroundings) -> TempDir {
    let dir = tempfile::tempdir().unwrap();
    let opts = GenerateOptions {
        size: 24,
        views: 8,
        seed: 11,
        surroundings,
        ..GenerateOptions::default()
    };
    generate(&opts, dir.path()).unwrap();
    dir
}

#[test]
fn photos_without_alpha_get_a_learned_background_and_unbounded_space() {
    // A stated colour: known background, bounded.
    let plain = Scene::load(
        surrounded(Surroundings::Plain).path(),
        &LoadOptions::default(),
    )
    .unwrap();
    assert!(matches!(plain.background, Background::Colour(_)) && !plain.unbounded);
    // A sky at infinity and a stated box: learned background, bounded by the box.
    let sky_dir = surrounded(Surroundings::Sky);
    let sky = Scene::load(sky_dir.path(), &LoadOptions::default()).unwrap();
    assert_eq!(sky.background, Background::Learned);
    assert!(!sky.unbounded && sky.aabb.min == Vec3::splat(-1.0));
    // Pixels of the sky have no ground-truth depth; the room's walls have.
    let unknown = |s: &Scene| {
        s.frames
            .iter()
            .flat_map(|f| f.depth.as_ref().unwrap())
            .filter(|d| **d == 0.0)
            .count()
    };
    assert!(unknown(&sky) > 100);
    // A room with no box and no background: learned background, contracted space, far
    // beyond the cameras.
    let room = Scene::load(
        surrounded(Surroundings::Room).path(),
        &LoadOptions::default(),
    )
    .unwrap();
    assert_eq!(room.background, Background::Learned);
    assert!(room.unbounded && room.far > 50.0 * room.aabb.size().max_element());
    assert_eq!(unknown(&room), 0);
    // The user's colour wins over learning.
    let forced = LoadOptions {
        background: Some([0.0, 0.0, 0.0]),
        ..LoadOptions::default()
    };
    let s = Scene::load(sky_dir.path(), &forced).unwrap();
    assert_eq!(s.background, Background::Colour([0.0; 3]));
}

/// A `.npy` file with the given dtype descriptor, shape and little-endian payload.
fn npy_bytes(descr: &str, shape: &str, payload: &[u8]) -> Vec<u8> {
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(payload);
    out
}

#[test]
fn npy_depth_maps_load_like_png_ones() {
    let d = fixture(CameraRig::Orbit, 24, 8);
    let png = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    // Every frame's depth as float32 metres (H, W), frame 1's as uint16 millimetres
    // (H, W, 1), both through depth_unit_scale_factor as nerfstudio reads them.
    let mut frames = Vec::new();
    for (i, f) in png.frames.iter().enumerate() {
        let depth = f.depth.as_ref().unwrap();
        let name = format!("depths/frame_{i:05}.npy");
        let bytes = if i == 1 {
            let mm: Vec<u8> = depth
                .iter()
                .flat_map(|d| ((d * 1000.0).round() as u16).to_le_bytes())
                .collect();
            npy_bytes("<u2", "(24, 24, 1)", &mm)
        } else {
            let m: Vec<u8> = depth
                .iter()
                .flat_map(|d| (d * 1000.0).to_le_bytes())
                .collect();
            npy_bytes("<f4", "(24, 24)", &m)
        };
        std::fs::write(d.path().join(&name), bytes).unwrap();
        frames.push(name);
    }
    edit(d.path(), |doc| {
        doc["depth_unit_scale_factor"] = json!(1e-3);
        for (f, name) in doc["frames"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .zip(&frames)
        {
            f["depth_file_path"] = json!(name);
        }
    });
    let npy = Scene::load(d.path(), &LoadOptions::default()).unwrap();
    for (a, b) in png.frames.iter().zip(&npy.frames) {
        let (a, b) = (a.depth.as_ref().unwrap(), b.depth.as_ref().unwrap());
        assert!(
            a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-3),
            "{:?}",
            &b[..4]
        );
    }
    // A depth array of the wrong size names the frame's field.
    std::fs::write(
        d.path().join(&frames[2]),
        npy_bytes("<f4", "(2, 2)", &[0u8; 16]),
    )
    .unwrap();
    let msg = Scene::load(d.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("frames[2].depth_file_path") && msg.contains("2×2"),
        "{msg}"
    );
}

#[test]
fn missing_images_are_named_in_one_error() {
    let d = fixture(CameraRig::Orbit, 16, 8);
    for i in [2, 5, 6] {
        std::fs::remove_file(d.path().join(format!("images/frame_{i:05}.png"))).unwrap();
    }
    let msg = Scene::load(d.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(msg.contains("3 of 8 frames"), "{msg}");
    for i in [2, 5, 6] {
        assert!(
            msg.contains(&format!("images/frame_{i:05}.png (frames[{i}])")),
            "{msg}"
        );
    }
}

#[test]
fn working_resolution_caps_the_longest_side() {
    let d = fixture(CameraRig::Orbit, 24, 8);
    let opts = LoadOptions {
        max_side: Some(12),
        ..LoadOptions::default()
    };
    let s = Scene::load(d.path(), &opts).unwrap();
    assert_eq!(s.resolution(), (12, 12));
    assert!(s
        .frames
        .iter()
        .all(|f| f.depth.as_ref().unwrap().len() == 144));
    let bad = LoadOptions {
        max_side: Some(2),
        ..LoadOptions::default()
    };
    let msg = Scene::load(d.path(), &bad).unwrap_err().to_string();
    assert!(msg.contains("max_side"), "{msg}");
}
