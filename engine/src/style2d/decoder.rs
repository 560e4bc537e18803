//! The trainable decoder: the mirror of the encoder from relu4_1 back to RGB. Each encoder
//! convolution (in → out) becomes a decoder convolution (out → in) in reverse order, each
//! encoder max-pool a 2× nearest upsampling, with reflection padding and ReLU everywhere but
//! after the last convolution — for VGG-19 exactly AdaIN's published decoder, whose
//! `decoder.pth` loads here.
//!
//! Saved as safetensors: `decoder.{k}.weight` `[out, in, 3, 3]` and `decoder.{k}.bias` for
//! k = 0, 1, … in forward order, with metadata `format` = `stylenerf-adain-decoder/1`, `arch`,
//! and `encoder` (the encoder's source, to catch pairing a decoder with another encoder).
//!
//! A general decoder for the bundled encoder ships in the binary ([`Decoder::bundled`]): trained
//! once, offline, on 502 photos, 147 paintings and drawings and the three procedural styles
//! (`assets/decoder/PROVENANCE.md`), it is where every job's `decoder_pretrain` starts.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};

use super::arch::VggArch;
use super::conv::conv2d;
use super::pad::reflection_pad2d;
use super::resample::upsample_nearest2x;
use super::st_file;
use super::weights::{legacy_pickle_error, read_state_dict, take_conv};
use crate::named::{load_vars, tensors_of};
use crate::rng::Rng;
use crate::{EngineError, Result};

const FORMAT_TAG: &str = "stylenerf-adain-decoder/1";

/// Bytes of the bundled general decoder (see `assets/decoder/PROVENANCE.md`).
const BUNDLED_DECODER: &[u8] =
    include_bytes!("../../../assets/decoder/vgg16_hed_general.safetensors");

/// Name the bundled decoder is reported under.
pub const BUNDLED_DECODER_NAME: &str = "bundled:vgg16_hed_general";

/// Sequential indices of the convolutions in AdaIN's `decoder.pth` (VGG-19 mirror).
const ADAIN_DECODER_PTH: [usize; 9] = [1, 5, 8, 11, 14, 18, 21, 25, 28];

/// One decoder convolution's shape and what follows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Step {
    c_in: usize,
    c_out: usize,
    relu: bool,
    upsample_after: bool,
}

fn mirror(arch: VggArch) -> Vec<Step> {
    let convs = arch.convs();
    convs
        .iter()
        .rev()
        .enumerate()
        .map(|(k, s)| Step {
            c_in: s.c_out,
            c_out: s.c_in,
            relu: k + 1 < convs.len(),
            upsample_after: s.pool_before,
        })
        .collect()
}

/// The decoder: trainable convolution weights as [`Var`]s.
#[derive(Debug, Clone)]
pub struct Decoder {
    arch: VggArch,
    steps: Vec<Step>,
    /// `(weight [out, in, 3, 3], bias [out])` per step.
    params: Vec<(Var, Var)>,
}

impl Decoder {
    /// A freshly initialised decoder, seeded: He-uniform weights and zero biases, except the
    /// last convolution, whose weights are scaled by 0.1 and whose bias is mid-grey, so a new
    /// decoder starts from a flat grey image instead of saturated noise (a decoder trained
    /// from scratch in a few hundred steps otherwise spends them undoing that noise).
    pub fn new(arch: VggArch, seed: u64, device: &Device) -> Result<Self> {
        let mut rng = Rng::new(seed);
        let steps = mirror(arch);
        let params = steps
            .iter()
            .map(|s| {
                let fan_in = s.c_in * 9;
                let last = !s.relu;
                let bound = (6.0 / fan_in as f32).sqrt() * if last { 0.1 } else { 1.0 };
                let w: Vec<f32> = (0..s.c_out * fan_in)
                    .map(|_| (rng.uniform() * 2.0 - 1.0) * bound)
                    .collect();
                let w = Tensor::from_vec(w, (s.c_out, s.c_in, 3, 3), device)?;
                let b = Tensor::full(if last { 0.5f32 } else { 0.0 }, s.c_out, device)?;
                Ok((Var::from_tensor(&w)?, Var::from_tensor(&b)?))
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            arch,
            steps,
            params,
        })
    }

    pub fn arch(&self) -> VggArch {
        self.arch
    }

    /// Decodes relu4_1-shaped features `[B, 512, h, w]` to RGB `[B, 3, 8h, 8w]` (not clamped:
    /// roughly [0, 1]).
    pub fn forward(&self, feat: &Tensor) -> candle_core::Result<Tensor> {
        let mut h = feat.clone();
        for (s, (w, b)) in self.steps.iter().zip(&self.params) {
            h = conv2d(&reflection_pad2d(&h, 1)?, w.as_tensor())?
                .broadcast_add(&b.as_tensor().reshape((1, s.c_out, 1, 1))?)?;
            if s.relu {
                h = h.relu()?;
            }
            if s.upsample_after {
                h = upsample_nearest2x(&h)?;
            }
        }
        Ok(h)
    }

    /// The trainable variables with stable names (`decoder.{k}.weight` / `.bias`).
    pub fn vars(&self) -> Vec<(String, Var)> {
        self.params
            .iter()
            .enumerate()
            .flat_map(|(k, (w, b))| {
                [
                    (format!("decoder.{k}.weight"), w.clone()),
                    (format!("decoder.{k}.bias"), b.clone()),
                ]
            })
            .collect()
    }

    /// The weights as named tensors (for checkpoints).
    pub fn tensors(&self) -> Vec<(String, Tensor)> {
        tensors_of(&self.vars())
    }

    /// Overwrites the weights from named tensors as produced by [`Self::tensors`] (read from
    /// `source`).
    pub fn load_tensors(&self, tensors: &HashMap<String, Tensor>, source: &Path) -> Result<()> {
        load_vars(&self.vars(), tensors, source)
    }

    /// Saves the decoder as safetensors (f32); `encoder` names the encoder it was trained
    /// with.
    pub fn save(&self, path: &Path, encoder: &str) -> Result<()> {
        self.save_as(path, encoder, DType::F32)
    }

    /// [`Self::save`] with the weights stored as `dtype` (F16 halves a decoder meant to be
    /// shipped; [`Self::load`] reads it back as f32).
    pub fn save_as(&self, path: &Path, encoder: &str, dtype: DType) -> Result<()> {
        let meta = [
            ("format", FORMAT_TAG.to_string()),
            ("arch", self.arch.name().to_string()),
            ("encoder", encoder.to_string()),
        ];
        let tensors = self
            .tensors()
            .into_iter()
            .map(|(k, t)| Ok((k, t.to_dtype(dtype)?)))
            .collect::<Result<Vec<_>>>()?;
        st_file::save(path, &tensors, &meta)
    }

    /// Loads a decoder saved by [`Self::save`] or AdaIN's `decoder.pth` (zip format; VGG-19
    /// mirror). Returns it with the name of the encoder it was trained with, when recorded.
    pub fn load(path: &Path, device: &Device) -> Result<(Self, Option<String>)> {
        let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
        if bytes.starts_with(b"PK\x03\x04") {
            let sd = read_state_dict(path)?;
            let dec = Self::new(VggArch::Vgg19, 0, device)?;
            for ((s, (w, b)), idx) in dec.steps.iter().zip(&dec.params).zip(ADAIN_DECODER_PTH) {
                let what = format!("decoder conv {idx}");
                let c = take_conv(
                    path,
                    &sd,
                    &format!("{idx}.weight"),
                    &format!("{idx}.bias"),
                    (&what, s.c_out, s.c_in, 3),
                )?;
                w.set(&c.weight.to_device(device)?)?;
                b.set(&c.bias.to_device(device)?)?;
            }
            return Ok((dec, Some("AdaIN vgg_normalised (decoder.pth)".into())));
        }
        if bytes.first() == Some(&0x80) {
            return Err(legacy_pickle_error(path));
        }
        Self::from_safetensors(path, &bytes, device)
    }

    /// The general decoder bundled with the binary, with the source of the encoder it was
    /// trained for (the bundled encoder's).
    pub fn bundled(device: &Device) -> Result<(Self, String)> {
        let (dec, encoder) =
            Self::from_safetensors(Path::new(BUNDLED_DECODER_NAME), BUNDLED_DECODER, device)?;
        let encoder = encoder.ok_or_else(|| {
            EngineError::artifact(
                Path::new(BUNDLED_DECODER_NAME),
                "the bundled decoder does not record its encoder",
            )
        })?;
        Ok((dec, encoder))
    }

    /// The bundled general decoder when `encoder_source` (an encoder's
    /// [`source`](crate::style2d::encoder::VggEncoder::source)) is the one it was trained for;
    /// `None` for any other encoder, whose features it cannot decode.
    pub fn bundled_for(encoder_source: &str, device: &Device) -> Result<Option<Self>> {
        let (dec, trained_for) = Self::bundled(device)?;
        Ok((trained_for == encoder_source).then_some(dec))
    }

    /// Reads the project's safetensors layout from `bytes` (read from `path`).
    fn from_safetensors(
        path: &Path,
        bytes: &[u8],
        device: &Device,
    ) -> Result<(Self, Option<String>)> {
        let meta = st_file::metadata(path, bytes)?;
        if meta.get("format").map(String::as_str) != Some(FORMAT_TAG) {
            return Err(EngineError::artifact(
                path,
                format!("not a decoder file: metadata `format` is not {FORMAT_TAG}"),
            ));
        }
        let arch = meta
            .get("arch")
            .and_then(|a| VggArch::parse(a))
            .ok_or_else(|| EngineError::artifact(path, "decoder metadata lacks a valid `arch`"))?;
        let dec = Self::new(arch, 0, device)?;
        let tensors = candle_core::safetensors::load_buffer(bytes, device)?;
        dec.load_tensors(&tensors, path)?;
        Ok((dec, meta.get("encoder").cloned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;

    #[test]
    fn vgg19_mirror_is_adains_decoder() {
        let s = mirror(VggArch::Vgg19);
        let shapes: Vec<(usize, usize)> = s.iter().map(|s| (s.c_in, s.c_out)).collect();
        assert_eq!(
            shapes,
            vec![
                (512, 256),
                (256, 256),
                (256, 256),
                (256, 256),
                (256, 128),
                (128, 128),
                (128, 64),
                (64, 64),
                (64, 3)
            ]
        );
        let ups: Vec<usize> = s
            .iter()
            .enumerate()
            .filter(|(_, s)| s.upsample_after)
            .map(|(i, _)| i)
            .collect();
        assert_eq!(ups, vec![0, 4, 6]);
        assert!(!s.last().unwrap().relu && s[..8].iter().all(|s| s.relu));
    }

    /// A 32×48 test image (the GPU trainer's self-test input, `scripts/train_decoder_gpu.py`).
    fn test_image(dev: &Device) -> Tensor {
        let (h, w) = (32, 48);
        let mut v = vec![0f32; 3 * h * w];
        for y in 0..h {
            for x in 0..w {
                let (u, t) = (x as f32 / (w - 1) as f32, y as f32 / (h - 1) as f32);
                let px = [u, t, 0.5 + 0.5 * (6.0 * u * t).sin()];
                for c in 0..3 {
                    v[(c * h + y) * w + x] = (px[c] * 255.0).round() / 255.0;
                }
            }
        }
        Tensor::from_vec(v, (1, 3, h, w), dev).unwrap()
    }

    #[test]
    fn the_bundled_decoder_is_trained_for_the_bundled_encoder() {
        use crate::style2d::encoder::VggEncoder;
        use crate::style2d::weights::EncoderWeights;
        let dev = Device::Cpu;
        let (dec, trained_with) = Decoder::bundled(&dev).unwrap();
        let weights = EncoderWeights::bundled().unwrap();
        assert_eq!(trained_with, weights.source);
        let enc = VggEncoder::new(&weights, &dev).unwrap();
        let x = test_image(&dev);
        let y = dec.forward(&enc.relu4_1(&x).unwrap()).unwrap();
        // Its output as recorded when the asset was added (f16 weights computed in f32: only
        // the summation order may differ between machines).
        let means = y.mean((0, 2, 3)).unwrap().to_vec1::<f32>().unwrap();
        let row = y.get(0).unwrap().get(1).unwrap().get(16).unwrap();
        let row = row.narrow(0, 0, 6).unwrap().to_vec1::<f32>().unwrap();
        let recorded_means = [0.552_460_9, 0.525_724_9, 0.692_674_1];
        let recorded_row = [
            0.629_265_8,
            0.621_904_4,
            0.561_002_3,
            0.621_704_6,
            0.664_216_9,
            0.615_587_8,
        ];
        for (got, want) in means
            .iter()
            .chain(&row)
            .zip(recorded_means.iter().chain(&recorded_row))
        {
            assert!((got - want).abs() < 1e-3, "{means:?} {row:?}");
        }
        // It is a trained AdaIN decoder: stylizing one painted style with another's statistics
        // lands far closer to that style (AdaIN's style loss) than a fresh decoder does.
        let paint = |name: &str| {
            let img = crate::style2d::painted::paint(name, 64).unwrap();
            crate::style2d::images::hwc_to_tensor(img.as_raw(), 64, 64, &dev).unwrap()
        };
        let style_loss = |decoder: Decoder| {
            let net = crate::style2d::network::AdaInNet {
                encoder: enc.clone(),
                decoder,
            };
            let target = net.style_target(&paint("mosaic")).unwrap();
            let l = net.losses(&paint("waves"), &target).unwrap();
            l.style.to_scalar::<f32>().unwrap()
        };
        let (trained, fresh) = (
            style_loss(dec),
            style_loss(Decoder::new(VggArch::Vgg16, 0, &dev).unwrap()),
        );
        println!("style loss {trained} fresh {fresh}");
        assert!(trained < 0.5 * fresh, "{trained} vs {fresh}");
    }

    #[test]
    fn shapes_save_and_load() {
        let dec = Decoder::new(VggArch::Vgg16, 1, &Device::Cpu).unwrap();
        let x = Tensor::rand(0f32, 1.0, (2, 512, 2, 3), &Device::Cpu).unwrap();
        let y = dec.forward(&x).unwrap();
        assert_eq!(y.dims(), &[2, 3, 16, 24]);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("dec.safetensors");
        dec.save(&p, "enc-x").unwrap();
        let (back, enc) = Decoder::load(&p, &Device::Cpu).unwrap();
        assert_eq!(enc.as_deref(), Some("enc-x"));
        let d = gradcheck::max_abs(&(back.forward(&x).unwrap() - y).unwrap());
        assert_eq!(d, 0.0);
        std::fs::write(&p, b"\x80\x02junk").unwrap();
        assert!(Decoder::load(&p, &Device::Cpu)
            .unwrap_err()
            .to_string()
            .contains("legacy"));
    }

    #[test]
    fn decoder_block_gradient_matches_finite_differences() {
        // conv → relu → upsample → pad → conv, as composed in `forward`, w.r.t. the input
        // and (through the same ops) the weights.
        let w1 = gradcheck::random(&[3, 2, 3, 3], 20);
        let w2 = gradcheck::random(&[2, 3, 3, 3], 21);
        gradcheck::check(&gradcheck::random(&[1, 2, 3, 2], 22), |x| {
            let h = conv2d(&reflection_pad2d(x, 1)?, &w1)?.relu()?;
            conv2d(&reflection_pad2d(&upsample_nearest2x(&h)?, 1)?, &w2)
        });
        let x = gradcheck::random(&[1, 2, 3, 2], 23);
        gradcheck::check(&w1, |w| {
            let h = conv2d(&reflection_pad2d(&x, 1)?, w)?.relu()?;
            conv2d(&reflection_pad2d(&upsample_nearest2x(&h)?, 1)?, &w2)
        });
    }
}
