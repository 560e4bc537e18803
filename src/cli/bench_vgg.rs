//! `stylenerf bench vgg`: timing of the frozen VGG encoder — forward to relu4_1 and
//! forward + backward to the input image — at 128² and 256², with the engine's convolution
//! (row-wise im2col, input gradient only for frozen weights) against candle's conv2d (tiled
//! im2col; it also computes the kernel gradients).

use std::time::Instant;

use candle_core::{Device, Tensor, Var};
use clap::Args;
use stylenerf_engine::style2d::encoder::{ConvPath, VggEncoder};
use stylenerf_engine::style2d::weights::EncoderWeights;

#[derive(Debug, Args)]
pub struct BenchVggArgs {
    /// Encoder weights (default: the bundled VGG-16).
    #[arg(long)]
    encoder: Option<std::path::PathBuf>,
    /// Image sides to measure.
    #[arg(long, value_delimiter = ',', default_values_t = [128usize, 256])]
    sizes: Vec<usize>,
    /// Timed repetitions per measurement (the median is reported), after one warm-up.
    #[arg(long, default_value_t = 3)]
    reps: usize,
}

fn median_secs(reps: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<f64> {
    f()?;
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f().map(|_| s.elapsed().as_secs_f64())
        })
        .collect::<anyhow::Result<_>>()?;
    t.sort_by(f64::total_cmp);
    Ok(t[t.len() / 2])
}

pub fn run(a: BenchVggArgs) -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let weights = EncoderWeights::load_or_bundled(a.encoder.as_deref())?;
    let engine = VggEncoder::new(&weights, &dev)?;
    let candle = engine.clone().with_conv_path(ConvPath::Candle);
    println!(
        "encoder {} ({}), {} threads, median of {}",
        weights.arch.name(),
        weights.source,
        candle_core::utils::get_num_threads(),
        a.reps
    );
    println!(
        "| size | forward, candle (s) | forward, engine (s) | speed-up | fwd+bwd, candle (s) | fwd+bwd, engine (s) | speed-up |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &s in &a.sizes {
        let x = Tensor::rand(0f32, 1.0, (1, 3, s, s), &dev)?;
        let var = Var::from_tensor(&x)?;
        let fwd = |enc: &VggEncoder| median_secs(a.reps, || Ok(enc.relu4_1(&x).map(drop)?));
        let fb = |enc: &VggEncoder| {
            median_secs(a.reps, || {
                let g = enc
                    .relu4_1(var.as_tensor())?
                    .sqr()?
                    .mean_all()?
                    .backward()?;
                anyhow::ensure!(
                    g.get(var.as_tensor()).is_some(),
                    "no gradient reached the image"
                );
                Ok(())
            })
        };
        let (fc, fe) = (fwd(&candle)?, fwd(&engine)?);
        let (bc, be) = (fb(&candle)?, fb(&engine)?);
        println!(
            "| {s}² | {fc:.3} | {fe:.3} | {:.2}× | {bc:.3} | {be:.3} | {:.2}× |",
            fc / fe,
            bc / be
        );
    }
    Ok(())
}
