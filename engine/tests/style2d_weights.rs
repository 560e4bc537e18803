//! Weight import: every supported source format, written as a small synthetic fixture at test
//! time (Keras .h5 with a pure-Rust HDF5 writer, PyTorch zip .pth with a minimal pickle
//! writer, safetensors), and every error a user can hit.

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use stylenerf_engine::style2d::arch::VggArch;
use stylenerf_engine::style2d::weights::{
    import, ChannelOrder, EncoderWeights, TorchvisionPreprocess, WeightFormat,
};

/// Deterministic values for tensor number `seed`: distinct per element and per tensor.
fn values(n: usize, seed: usize) -> Vec<f32> {
    (0..n)
        .map(|i| (((i * 7919 + seed * 104_729) % 2003) as f32 / 2003.0 - 0.5) * 0.1)
        .collect()
}

/// The OIHW weight and bias that every fixture stores for conv number `i` of `arch`.
fn reference(arch: VggArch, i: usize) -> (Vec<f32>, Vec<f32>) {
    let s = arch.convs()[i];
    (
        values(s.c_out * s.c_in * 9, 2 * i),
        values(s.c_out, 2 * i + 1),
    )
}

fn oihw_to_hwio(w: &[f32], o: usize, i: usize) -> Vec<f32> {
    let mut out = vec![0f32; w.len()];
    for oo in 0..o {
        for ii in 0..i {
            for k in 0..9 {
                out[(k * i + ii) * o + oo] = w[(oo * i + ii) * 9 + k];
            }
        }
    }
    out
}

fn assert_matches_reference(w: &EncoderWeights, arch: VggArch, tol: f32) {
    assert_eq!(w.arch, arch);
    assert_eq!(w.convs.len(), arch.convs().len());
    for (i, conv) in w.convs.iter().enumerate() {
        let (rw, rb) = reference(arch, i);
        let got = conv.weight.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let gotb = conv.bias.to_vec1::<f32>().unwrap();
        let err = got
            .iter()
            .zip(&rw)
            .chain(gotb.iter().zip(&rb))
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(err <= tol, "conv {i}: max error {err}");
    }
}

fn keras_h5(dir: &Path, keras2: bool) -> PathBuf {
    use hdf5_writer::{DatasetBuilder, Hdf5Builder, Hdf5Writer, WriteOptions};
    let arch = VggArch::Vgg16;
    let mut b = Hdf5Builder::new();
    let mut per_block = HashMap::new();
    for (i, s) in arch.convs().iter().enumerate() {
        let block: usize = s.name[4..5].parse().unwrap();
        let j = per_block.entry(block).or_insert(0usize);
        let (w, bias) = reference(arch, i);
        let (wk, bk) = if keras2 {
            let g = format!("block{block}_conv{}/block{block}_conv{}", *j + 1, *j + 1);
            (format!("{g}/kernel:0"), format!("{g}/bias:0"))
        } else {
            let suffix = if *j == 0 {
                String::new()
            } else {
                format!("_{j}")
            };
            let g = format!("block{block}/layers/conv2d{suffix}/vars");
            (format!("{g}/0"), format!("{g}/1"))
        };
        *j += 1;
        let hwio = oihw_to_hwio(&w, s.c_out, s.c_in);
        b = b
            .dataset(
                DatasetBuilder::typed_data(wk, vec![3, 3, s.c_in as u64, s.c_out as u64], &hwio)
                    .unwrap(),
            )
            .dataset(DatasetBuilder::typed_data(bk, vec![s.c_out as u64], &bias).unwrap());
    }
    // HED's side outputs live beside the backbone and must be ignored.
    b = b.dataset(
        DatasetBuilder::typed_data("dsn1/vars/0", vec![1, 1, 64, 1], &[0f32; 64]).unwrap(),
    );
    let bytes = Hdf5Writer::new(std::io::Cursor::new(Vec::new()), WriteOptions::default())
        .finish(b.into_plan().unwrap())
        .unwrap()
        .into_inner();
    let p = dir.join(if keras2 {
        "keras2.h5"
    } else {
        "hed.weights.h5"
    });
    std::fs::write(&p, bytes).unwrap();
    p
}

/// A minimal pickle (protocol 2) of an OrderedDict of tensors, as `torch.save` writes it.
fn pickle_state_dict(tensors: &[(String, Vec<usize>)]) -> Vec<u8> {
    let mut p = vec![0x80, 2];
    let global = |p: &mut Vec<u8>, m: &str, c: &str| {
        p.push(b'c');
        p.extend(format!("{m}\n{c}\n").as_bytes());
    };
    let unicode = |p: &mut Vec<u8>, s: &str| {
        p.push(b'X');
        p.extend((s.len() as u32).to_le_bytes());
        p.extend(s.as_bytes());
    };
    let int = |p: &mut Vec<u8>, v: usize| {
        p.push(b'J');
        p.extend((v as i32).to_le_bytes());
    };
    global(&mut p, "collections", "OrderedDict");
    p.extend(b")R(");
    for (key, (name, shape)) in tensors.iter().enumerate() {
        unicode(&mut p, name);
        global(&mut p, "torch._utils", "_rebuild_tensor_v2");
        p.push(b'(');
        p.push(b'(');
        unicode(&mut p, "storage");
        global(&mut p, "torch", "FloatStorage");
        unicode(&mut p, &key.to_string());
        unicode(&mut p, "cpu");
        int(&mut p, shape.iter().product());
        p.extend(b"tQ");
        int(&mut p, 0);
        p.push(b'(');
        for &d in shape {
            int(&mut p, d);
        }
        p.push(b't');
        p.push(b'(');
        let mut stride = 1;
        let mut strides = vec![0; shape.len()];
        for (k, &d) in shape.iter().enumerate().rev() {
            strides[k] = stride;
            stride *= d;
        }
        for s in strides {
            int(&mut p, s);
        }
        p.push(b't');
        p.push(0x89);
        global(&mut p, "collections", "OrderedDict");
        p.extend(b")RtR");
    }
    p.extend(b"u.");
    p
}

/// Writes `tensors` as a zip-format .pth (what torch ≥ 1.6 saves).
fn write_pth(path: &Path, tensors: &[(String, Vec<usize>, Vec<f32>)]) {
    let mut zip = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    let meta: Vec<(String, Vec<usize>)> = tensors
        .iter()
        .map(|(n, s, _)| (n.clone(), s.clone()))
        .collect();
    zip.start_file("archive/data.pkl", opts).unwrap();
    zip.write_all(&pickle_state_dict(&meta)).unwrap();
    for (key, (_, _, data)) in tensors.iter().enumerate() {
        zip.start_file(format!("archive/data/{key}"), opts).unwrap();
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        zip.write_all(&bytes).unwrap();
    }
    zip.start_file("archive/version", opts).unwrap();
    zip.write_all(b"3\n").unwrap();
    zip.finish().unwrap();
}

/// State-dict entries for `arch` under the given conv names.
fn state_dict(arch: VggArch, names: &[String]) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let mut out = Vec::new();
    for (i, (s, n)) in arch.convs().iter().zip(names).enumerate() {
        let (w, b) = reference(arch, i);
        out.push((format!("{n}.weight"), vec![s.c_out, s.c_in, 3, 3], w));
        out.push((format!("{n}.bias"), vec![s.c_out], b));
    }
    out
}

fn torchvision_names(arch: VggArch) -> Vec<String> {
    let idx: &[usize] = match arch {
        VggArch::Vgg16 => &[0, 2, 5, 7, 10, 12, 14, 17],
        VggArch::Vgg19 => &[0, 2, 5, 7, 10, 12, 14, 16, 19],
    };
    idx.iter().map(|i| format!("features.{i}")).collect()
}

fn vgg_normalised_dict() -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let names: Vec<String> = [2, 5, 9, 12, 16, 19, 22, 25, 29]
        .iter()
        .map(|i| i.to_string())
        .collect();
    let mut sd = state_dict(VggArch::Vgg19, &names);
    // A BGR swap scaled to 0–255 minus a mean, as in the real file.
    let pre = vec![0., 0., 255., 0., 255., 0., 255., 0., 0.];
    sd.push(("0.weight".into(), vec![3, 3, 1, 1], pre));
    sd.push(("0.bias".into(), vec![3], vec![-103.9, -116.8, -123.7]));
    sd
}

fn write_safetensors(path: &Path, sd: &[(String, Vec<usize>, Vec<f32>)]) {
    let map: HashMap<String, Tensor> = sd
        .iter()
        .map(|(n, s, d)| {
            (
                n.clone(),
                Tensor::from_vec(d.clone(), s.as_slice(), &Device::Cpu).unwrap(),
            )
        })
        .collect();
    candle_core::safetensors::save(&map, path).unwrap();
}

fn err_of(path: &Path, format: WeightFormat) -> String {
    import(path, format, TorchvisionPreprocess::Imagenet)
        .unwrap_err()
        .to_string()
}

#[test]
fn keras_h5_hed_and_keras2_layouts() {
    let dir = tempfile::tempdir().unwrap();
    for keras2 in [false, true] {
        let p = keras_h5(dir.path(), keras2);
        let w = import(&p, WeightFormat::Auto, TorchvisionPreprocess::Imagenet).unwrap();
        assert_matches_reference(&w, VggArch::Vgg16, 0.0);
        assert_eq!(w.preprocess.channel_order, ChannelOrder::Bgr);
        assert_eq!(w.preprocess.scale, 255.0);
        let mean0 = if keras2 { 103.939 } else { 104.00699 };
        assert_eq!(w.preprocess.mean[0], mean0);
        assert!(w.source.contains("sha256"));
    }
}

#[test]
fn vgg_normalised_pth() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("vgg_normalised.pth");
    write_pth(&p, &vgg_normalised_dict());
    for format in [WeightFormat::Auto, WeightFormat::VggNormalisedPth] {
        let w = import(&p, format, TorchvisionPreprocess::Imagenet).unwrap();
        assert_matches_reference(&w, VggArch::Vgg19, 0.0);
        assert!(w.preprocess.conv.is_some());
        // The 1×1 conv maps RGB in [0, 1] to BGR·255 − mean.
        let (a, c) = w.input_transform().unwrap();
        assert_eq!(a[0], [0.0, 0.0, 255.0]);
        assert!((c[0] + 103.9).abs() < 1e-4);
    }
}

#[test]
fn torchvision_pth_and_safetensors() {
    let dir = tempfile::tempdir().unwrap();
    for arch in [VggArch::Vgg16, VggArch::Vgg19] {
        let sd = state_dict(arch, &torchvision_names(arch));
        let pth = dir.path().join(format!("{}.pth", arch.name()));
        write_pth(&pth, &sd);
        let st = dir.path().join(format!("{}.safetensors", arch.name()));
        write_safetensors(&st, &sd);
        for p in [&pth, &st] {
            let w = import(
                p,
                WeightFormat::TorchvisionPth,
                TorchvisionPreprocess::Imagenet,
            )
            .unwrap();
            assert_matches_reference(&w, arch, 0.0);
            assert_eq!(w.preprocess.channel_order, ChannelOrder::Rgb);
            assert_eq!(w.preprocess.std[0], 0.229);
            let auto = import(p, WeightFormat::Auto, TorchvisionPreprocess::Caffe).unwrap();
            assert_eq!(auto.arch, arch);
            assert_eq!(auto.preprocess.channel_order, ChannelOrder::Bgr);
        }
    }
}

#[test]
fn project_layout_round_trips_with_metadata() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("vgg_normalised.pth");
    write_pth(&src, &vgg_normalised_dict());
    let w = import(&src, WeightFormat::Auto, TorchvisionPreprocess::Imagenet).unwrap();
    for (dtype, tol) in [(DType::F32, 0.0), (DType::F16, 1e-4)] {
        let out = dir.path().join("enc.safetensors");
        w.save(&out, dtype).unwrap();
        let back = import(
            &out,
            WeightFormat::Safetensors,
            TorchvisionPreprocess::Imagenet,
        )
        .unwrap();
        assert_matches_reference(&back, VggArch::Vgg19, tol);
        assert_eq!(back.source, w.source);
        let (a, c) = back.input_transform().unwrap();
        let (a0, c0) = w.input_transform().unwrap();
        assert_eq!(a, a0);
        assert!((c[2] - c0[2]).abs() < 0.1);
    }
}

#[test]
fn errors_name_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    // Missing tensor.
    let mut sd = state_dict(VggArch::Vgg16, &torchvision_names(VggArch::Vgg16));
    sd.retain(|(n, _, _)| n != "features.10.weight");
    let p = dir.path().join("missing.pth");
    write_pth(&p, &sd);
    let e = err_of(&p, WeightFormat::Auto);
    assert!(
        e.contains("missing tensor `features.10.weight` (conv3_1)"),
        "{e}"
    );
    // Wrong shape.
    let mut sd = state_dict(VggArch::Vgg16, &torchvision_names(VggArch::Vgg16));
    sd[0] = (
        "features.0.weight".into(),
        vec![64, 3, 1, 9],
        sd[0].2.clone(),
    );
    let p = dir.path().join("shape.safetensors");
    write_safetensors(&p, &sd);
    let e = err_of(&p, WeightFormat::Auto);
    assert!(
        e.contains("expected shape [64, 3, 3, 3], found [64, 3, 1, 9]"),
        "{e}"
    );
    // Legacy pickle .pth: says so and how to convert.
    let p = dir.path().join("legacy.pth");
    std::fs::write(&p, b"\x80\x02\x8a\x0al\xfc\x9cF\xf9 j\xa8P\x19.").unwrap();
    let e = err_of(&p, WeightFormat::Auto);
    assert!(
        e.contains("legacy") && e.contains("torch.save(torch.load("),
        "{e}"
    );
    // Unknown file.
    let p = dir.path().join("notes.txt");
    std::fs::write(&p, b"these are not weights").unwrap();
    assert!(err_of(&p, WeightFormat::Auto).contains("unknown weight file format"));
    // Unknown layout inside a valid container.
    let p = dir.path().join("other.safetensors");
    write_safetensors(&p, &[("encoder.layer.0".into(), vec![2], vec![0.0, 1.0])]);
    assert!(err_of(&p, WeightFormat::Auto).contains("unknown weight layout"));
    // Format flag contradicting the file.
    let p = dir.path().join("tv.pth");
    write_pth(
        &p,
        &state_dict(VggArch::Vgg16, &torchvision_names(VggArch::Vgg16)),
    );
    let e = err_of(&p, WeightFormat::KerasH5);
    assert!(e.contains("needs an HDF5 file") && e.contains("zip"), "{e}");
    // HDF5 without a VGG inside.
    use hdf5_writer::{DatasetBuilder, Hdf5Builder, Hdf5Writer, WriteOptions};
    let plan = Hdf5Builder::new()
        .dataset(DatasetBuilder::typed_data("x", vec![2], &[1f32, 2.]).unwrap())
        .into_plan()
        .unwrap();
    let bytes = Hdf5Writer::new(std::io::Cursor::new(Vec::new()), WriteOptions::default())
        .finish(plan)
        .unwrap()
        .into_inner();
    let p = dir.path().join("empty.h5");
    std::fs::write(&p, bytes).unwrap();
    assert!(err_of(&p, WeightFormat::Auto).contains("no VGG-16 conv1_1 kernel found"));
}
