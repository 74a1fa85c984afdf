//! The image encoder of the semantic tokens: a small CNN trained from scratch
//! (no pretrained CLIP weights are reachable here) that turns each camera's
//! RGB image into per-pixel features, later lifted to 3D with the depth map.
//!
//! Input `[B*cams, 3, H, W]` u8 RGB (normalised inside); output
//! `[B*cams, C, H/s, W/s]` with C = `out_channels` (120, Table B) and output
//! stride s = `patch_size` (4: 128x128 -> 32x32).
//!
//! Architecture (a small U-Net / feature pyramid, all convolutions as
//! im2col + GEMM in channels-last layout, because candle's CPU `conv2d` runs at
//! ~10 GFLOP/s against ~85 for its matmul):
//! ```text
//! stem      s x s patchify conv, stride s            -> level 0: H/s,  widths[0]
//! level l   2x2 stride-2 conv (l > 0), then blocks[l] pre-activation
//!           residual blocks (norm, SiLU, 3x3 conv) x2 -> H/(s 2^l), widths[l]
//! heads     y_l = 1x1 conv(silu(norm(x_l))) -> C, summed top-down:
//!           y = head_0(x_0) + up2(head_1(x_1) + up2(head_2(x_2)))   (FPN-style)
//! ```
//! Defaults: widths 32 / 96 / 128 at strides 4 / 8 / 16, one block per level,
//! 0.58 M parameters, 0.77 GFLOP for 4 cameras. The receptive field of an
//! output pixel is about 112 px of the 128 px image (through level 2); the
//! full-resolution level is kept narrow because a 3x3 conv at 32x32 costs 4x
//! one at 16x16 and 16x one at 8x8 of the same width. Weights are stored in
//! PyTorch's layouts (`[out, in, kh, kw]`), named after the structure.
//!
//! Runtime note (2-core CPU): candle's element-wise ops use their own spinning
//! thread pool beside rayon's; run with `CANDLE_NUM_THREADS=1` (element-wise
//! ops on the calling thread, GEMMs still on rayon's threads); `policy::runtime`
//! sets it, and `flowram bench policy` times the encoder.

use candle_core::{DType, Tensor};
use candle_nn::{Init, VarBuilder};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::policy::error::{PolicyError, Result};
use crate::policy::kernels::conv_ops::{AddBias, AddUpsampled2, Im2Col, LayerNormSilu, Window};

/// Normalisation inside the residual blocks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum EncoderNorm {
    /// Per-pixel LayerNorm over channels (as ConvNeXt); batch-independent.
    #[default]
    ChannelLayerNorm,
    /// No normalisation (residual branches start at zero, so training is
    /// still stable for this depth).
    None,
}

/// Hyper-parameters of the image encoder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageEncoderConfig {
    /// Input height and width in pixels (128, Table B).
    pub image_size: usize,
    /// Side of the stem's patches = output stride (4: 128 -> 32).
    pub patch_size: usize,
    /// Channels of the output features, the embedding dim C (120).
    pub out_channels: usize,
    /// Channels of each pyramid level; level l has stride `patch_size * 2^l`
    /// (32 / 96 / 128).
    pub widths: Vec<usize>,
    /// Residual blocks per level (same length as `widths`).
    pub blocks: Vec<usize>,
    pub norm: EncoderNorm,
    /// Per-channel RGB mean and std (of pixel values in [0, 1]) used to
    /// normalise the input.
    pub pixel_mean: [f32; 3],
    pub pixel_std: [f32; 3],
}

impl Default for ImageEncoderConfig {
    fn default() -> Self {
        Self {
            image_size: 128,
            patch_size: 4,
            out_channels: 120,
            widths: vec![32, 96, 128],
            blocks: vec![1, 1, 1],
            norm: EncoderNorm::ChannelLayerNorm,
            pixel_mean: [0.485, 0.456, 0.406],
            pixel_std: [0.229, 0.224, 0.225],
        }
    }
}

impl ImageEncoderConfig {
    /// Floating-point operations (multiply and add counted apart) of the forward pass over
    /// `images` images: the convolutions' GEMMs (stem, 2x2 downsampling, 3x3 blocks, 1x1 heads);
    /// norms, activations and the top-down sums are left out (under 1 %). 0.77 GFLOP for 4
    /// cameras at the defaults.
    pub fn flops(&self, images: usize) -> f64 {
        let mut total = 0.0;
        let mut previous = 3usize;
        for (level, (&width, &blocks)) in self.widths.iter().zip(&self.blocks).enumerate() {
            let side = self.image_size / (self.patch_size << level);
            let pixels = (side * side) as f64;
            let into = if level == 0 { self.patch_size * self.patch_size * 3 } else { 4 * previous };
            total += 2.0 * pixels * (into * width) as f64;
            total += blocks as f64 * 2.0 * 2.0 * pixels * (9 * width * width) as f64;
            total += 2.0 * pixels * (width * self.out_channels) as f64;
            previous = width;
        }
        total * images as f64
    }

    /// Checks sizes and names the field that is wrong.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(PolicyError::Invalid(format!("image encoder config: {m}")));
        if self.patch_size == 0 || self.image_size == 0 || self.out_channels == 0 {
            return bad("image_size, patch_size and out_channels must be positive".into());
        }
        if self.widths.is_empty() || self.widths.len() != self.blocks.len() {
            return bad(format!(
                "widths ({}) and blocks ({}) need the same, non-zero length",
                self.widths.len(),
                self.blocks.len()
            ));
        }
        if self.widths.contains(&0) {
            return bad(format!("widths {:?} must all be positive", self.widths));
        }
        let coarsest = self.patch_size << (self.widths.len() - 1);
        if !self.image_size.is_multiple_of(coarsest) {
            return bad(format!(
                "image_size {} must be divisible by patch_size * 2^(levels-1) = {coarsest}",
                self.image_size
            ));
        }
        if self.pixel_std.iter().any(|&s| s.is_nan() || s <= 0.0) {
            return bad(format!("pixel_std {:?} must be positive", self.pixel_std));
        }
        Ok(())
    }
}

// Layers (channels-last).

/// A square convolution on `[N, H, W, Cin]` via im2col + GEMM. Weight stored
/// as `[Cout, Cin, k, k]` (PyTorch layout), bias `[Cout]`.
#[derive(Clone, Debug)]
struct ConvNhwc {
    weight: Tensor,
    bias: Tensor,
    window: Window,
}

impl ConvNhwc {
    fn new(cin: usize, cout: usize, window: Window, zero_init: bool, vb: VarBuilder) -> Result<Self> {
        let k = window.kernel;
        let init = if zero_init { Init::Const(0.0) } else { candle_nn::init::DEFAULT_KAIMING_NORMAL };
        let weight = vb.get_with_hints((cout, cin, k, k), "weight", init)?;
        let bias = vb.get_with_hints(cout, "bias", Init::Const(0.0))?;
        Ok(Self { weight, bias, window })
    }

    /// `[N, H, W, Cin]` -> `[N, Ho, Wo, Cout]`.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (n, h, w, cin) = x.dims4()?;
        let win = self.window;
        let cols = if win.kernel == 1 && win.stride == 1 && win.padding == 0 {
            x.reshape((n * h * w, cin))?
        } else {
            x.contiguous()?.apply_op1(Im2Col(win))?
        };
        self.forward_columns(&cols, (n, win.out_size(h), win.out_size(w)))
    }

    /// The GEMM half: im2col columns `[N*Ho*Wo, k*k*Cin]` (ordered ky, kx, c)
    /// -> `[N, Ho, Wo, Cout]`.
    fn forward_columns(&self, cols: &Tensor, (n, ho, wo): (usize, usize, usize)) -> Result<Tensor> {
        let (cout, cin, k, _) = self.weight.dims4()?;
        // [Cout, Cin, ky, kx] -> [(ky, kx, Cin), Cout] to match the column order.
        let w_mat = self.weight.permute((2, 3, 1, 0))?.reshape((k * k * cin, cout))?;
        let y = cols.matmul(&w_mat)?.apply_op2(&self.bias, AddBias)?;
        Ok(y.reshape((n, ho, wo, cout))?)
    }
}

/// `silu(norm(x))` over channels: the fused LayerNorm + SiLU, or plain SiLU
/// when the encoder has no normalisation.
#[derive(Clone, Debug)]
struct NormSilu {
    affine: Option<(Tensor, Tensor)>,
}

impl NormSilu {
    fn new(channels: usize, kind: EncoderNorm, vb: VarBuilder) -> Result<Self> {
        let affine = match kind {
            EncoderNorm::None => None,
            EncoderNorm::ChannelLayerNorm => Some((
                vb.get_with_hints(channels, "weight", Init::Const(1.0))?,
                vb.get_with_hints(channels, "bias", Init::Const(0.0))?,
            )),
        };
        Ok(Self { affine })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match &self.affine {
            None => Ok(x.silu()?),
            Some((gamma, beta)) => Ok(x.contiguous()?.apply_op3(gamma, beta, LayerNormSilu { eps: 1e-5 })?),
        }
    }
}

/// Pre-activation residual block: `x + conv2(silu(norm2(conv1(silu(norm1(x))))))`,
/// conv2 zero-initialised so each block starts as the identity.
#[derive(Clone, Debug)]
struct ResidualBlock {
    norm1: NormSilu,
    conv1: ConvNhwc,
    norm2: NormSilu,
    conv2: ConvNhwc,
}

const CONV3X3: Window = Window { kernel: 3, stride: 1, padding: 1 };

impl ResidualBlock {
    fn new(channels: usize, norm: EncoderNorm, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            norm1: NormSilu::new(channels, norm, vb.pp("norm1"))?,
            conv1: ConvNhwc::new(channels, channels, CONV3X3, false, vb.pp("conv1"))?,
            norm2: NormSilu::new(channels, norm, vb.pp("norm2"))?,
            conv2: ConvNhwc::new(channels, channels, CONV3X3, true, vb.pp("conv2"))?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.conv1.forward(&self.norm1.forward(x)?)?;
        let h = self.conv2.forward(&self.norm2.forward(&h)?)?;
        Ok((x + h)?)
    }
}

/// One pyramid level: optional stride-2 downsampling conv, then residual blocks.
#[derive(Clone, Debug)]
struct Level {
    down: Option<ConvNhwc>,
    blocks: Vec<ResidualBlock>,
}

/// Projection of one pyramid level to the output channels:
/// `1x1 conv(silu(norm(x)))`, `widths[l]` -> C.
#[derive(Clone, Debug)]
struct LevelHead {
    norm: NormSilu,
    proj: ConvNhwc,
}

impl LevelHead {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.proj.forward(&self.norm.forward(x)?)
    }
}

/// The image encoder (see the module docs).
#[derive(Clone, Debug)]
pub struct ImageEncoder {
    config: ImageEncoderConfig,
    stem: ConvNhwc,
    levels: Vec<Level>,
    /// `heads[l]`: level l's projection to the output channels.
    heads: Vec<LevelHead>,
}

impl ImageEncoder {
    /// Builds the encoder, creating (or loading) its weights under `vb`
    /// (names: `stem.*`, `levels.{l}.down.*`, `levels.{l}.blocks.{b}.*`,
    /// `heads.{l}.norm.*`, `heads.{l}.proj.*`).
    pub fn new(config: ImageEncoderConfig, vb: VarBuilder) -> Result<Self> {
        config.validate()?;
        let p = config.patch_size;
        let stem =
            ConvNhwc::new(3, config.widths[0], Window { kernel: p, stride: p, padding: 0 }, false, vb.pp("stem"))?;
        let mut levels = Vec::with_capacity(config.widths.len());
        let mut heads = Vec::with_capacity(config.widths.len());
        let one = Window { kernel: 1, stride: 1, padding: 0 };
        for (l, (&width, &n_blocks)) in config.widths.iter().zip(&config.blocks).enumerate() {
            let vb_l = vb.pp(format!("levels.{l}"));
            let down = if l == 0 {
                None
            } else {
                let window = Window { kernel: 2, stride: 2, padding: 0 };
                Some(ConvNhwc::new(config.widths[l - 1], width, window, false, vb_l.pp("down"))?)
            };
            let blocks = (0..n_blocks)
                .map(|b| ResidualBlock::new(width, config.norm, vb_l.pp(format!("blocks.{b}"))))
                .collect::<Result<_>>()?;
            levels.push(Level { down, blocks });
            let vb_h = vb.pp(format!("heads.{l}"));
            heads.push(LevelHead {
                norm: NormSilu::new(width, config.norm, vb_h.pp("norm"))?,
                proj: ConvNhwc::new(width, config.out_channels, one, false, vb_h.pp("proj"))?,
            });
        }
        Ok(Self { config, stem, levels, heads })
    }

    pub fn config(&self) -> &ImageEncoderConfig {
        &self.config
    }

    /// Checks the input and turns u8 RGB `[N, 3, H, W]` straight into the
    /// stem's im2col columns `[N * H/p * W/p, p * p * 3]` (ordered ky, kx, c),
    /// normalising `(x / 255 - mean) / std` on the way: one pass, no graph
    /// (the input needs no gradient).
    fn stem_columns(&self, images: &Tensor) -> Result<(Tensor, (usize, usize, usize))> {
        let size = self.config.image_size;
        let dims = images.dims();
        if dims.len() != 4 || dims[1] != 3 || dims[2] != size || dims[3] != size {
            return Err(PolicyError::Invalid(format!(
                "image encoder input must be [B*cams, 3, {size}, {size}] RGB, got {dims:?}"
            )));
        }
        if images.dtype() != DType::U8 {
            return Err(PolicyError::Invalid(format!(
                "image encoder input must be u8 RGB (0..=255), got {:?}",
                images.dtype()
            )));
        }
        let n = dims[0];
        let p = self.config.patch_size;
        let side = size / p;
        let (mean, std) = (self.config.pixel_mean, self.config.pixel_std);
        let scale: [f32; 3] = std::array::from_fn(|c| 1.0 / (255.0 * std[c]));
        let shift: [f32; 3] = std::array::from_fn(|c| -mean[c] / std[c]);
        let pixels = images.flatten_all()?.to_vec1::<u8>()?;
        let row_len = p * p * 3;
        let mut cols = vec![0f32; n * side * side * row_len];
        // One task per row of patches.
        cols.par_chunks_mut(side * row_len).enumerate().for_each(|(row, out)| {
            let (img, py) = (row / side, row % side);
            for px in 0..side {
                for ky in 0..p {
                    for kx in 0..p {
                        let (y, x) = (py * p + ky, px * p + kx);
                        for c in 0..3 {
                            let v = pixels[((img * 3 + c) * size + y) * size + x];
                            out[px * row_len + (ky * p + kx) * 3 + c] = v as f32 * scale[c] + shift[c];
                        }
                    }
                }
            }
        });
        let dev = self.stem.weight.device();
        let cols = Tensor::from_vec(cols, (n * side * side, row_len), dev)?.to_dtype(self.stem.weight.dtype())?;
        Ok((cols, (n, side, side)))
    }

    /// Per-pixel features, channels last: u8 `[N, 3, H, W]` ->
    /// `[N, H/s, W/s, C]` (the layout the semantic-token lifting wants).
    pub fn forward_channels_last(&self, images: &Tensor) -> Result<Tensor> {
        let (cols, out_dims) = self.stem_columns(images)?;
        let mut x = self.stem.forward_columns(&cols, out_dims)?;
        let mut level_features = Vec::with_capacity(self.levels.len());
        for level in &self.levels {
            if let Some(down) = &level.down {
                x = down.forward(&x)?;
            }
            for block in &level.blocks {
                x = block.forward(&x)?;
            }
            level_features.push(x.clone());
        }
        // Top-down: y_l = head_l(x_l) + up2(y_{l+1}).
        let mut y: Option<Tensor> = None;
        for (head, features) in self.heads.iter().zip(&level_features).rev() {
            let projected = head.forward(features)?;
            y = Some(match y {
                None => projected,
                Some(coarser) => projected.contiguous()?.apply_op2(&coarser.contiguous()?, AddUpsampled2)?,
            });
        }
        y.ok_or_else(|| PolicyError::Invalid("image encoder has no levels".into()))
    }

    /// Per-pixel features: u8 RGB `[N, 3, H, W]` (N = B*cams) ->
    /// `[N, C, H/s, W/s]` f32.
    pub fn forward(&self, images: &Tensor) -> Result<Tensor> {
        Ok(self.forward_channels_last(images)?.permute((0, 3, 1, 2))?.contiguous()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_encoder_costs_what_its_documentation_says() {
        let gflop = ImageEncoderConfig::default().flops(4) / 1e9;
        assert!((gflop - 0.77).abs() < 0.005, "{gflop} GFLOP for 4 cameras");
    }
    use candle_core::Device;
    use candle_nn::VarMap;

    /// Reference convolution (NCHW loops) to check im2col + GEMM.
    fn conv_reference(
        x: &[f64],
        (n, h, w, c): (usize, usize, usize, usize),
        wt: &[f64],
        cout: usize,
        win: Window,
    ) -> Vec<f64> {
        let (ho, wo, k) = (win.out_size(h), win.out_size(w), win.kernel);
        let mut out = vec![0.0; n * ho * wo * cout];
        for b in 0..n {
            for oy in 0..ho {
                for ox in 0..wo {
                    for o in 0..cout {
                        let mut s = 0.0;
                        for ky in 0..k {
                            for kx in 0..k {
                                let iy = (oy * win.stride + ky) as isize - win.padding as isize;
                                let ix = (ox * win.stride + kx) as isize - win.padding as isize;
                                if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                    continue;
                                }
                                for i in 0..c {
                                    let xv = x[((b * h + iy as usize) * w + ix as usize) * c + i];
                                    s += xv * wt[((o * c + i) * k + ky) * k + kx];
                                }
                            }
                        }
                        out[((b * ho + oy) * wo + ox) * cout + o] = s;
                    }
                }
            }
        }
        out
    }

    fn values(t: &Tensor) -> Vec<f64> {
        t.flatten_all().unwrap().to_dtype(DType::F64).unwrap().to_vec1().unwrap()
    }

    #[test]
    fn conv_nhwc_matches_reference_for_all_windows() {
        let dev = Device::Cpu;
        for win in [
            Window { kernel: 3, stride: 1, padding: 1 },
            Window { kernel: 2, stride: 2, padding: 0 },
            Window { kernel: 4, stride: 4, padding: 0 },
            Window { kernel: 3, stride: 2, padding: 1 },
        ] {
            let dims = (2, 8, 8, 3);
            let x = Tensor::randn(0f64, 1.0, dims, &dev).unwrap();
            let varmap = VarMap::new();
            let vb = VarBuilder::from_varmap(&varmap, DType::F64, &dev);
            let conv = ConvNhwc::new(3, 5, win, false, vb).unwrap();
            let y = conv.forward(&x).unwrap();
            let expected = conv_reference(&values(&x), dims, &values(&conv.weight), 5, win);
            let got = values(&y);
            assert_eq!(got.len(), expected.len());
            for (a, b) in got.iter().zip(&expected) {
                assert!((a - b).abs() < 1e-10, "{win:?}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn stem_columns_equal_normalised_im2col() {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let enc = ImageEncoder::new(small_config(), vb).unwrap();
        let images = random_images(2, 32, 5);
        let (cols, dims) = enc.stem_columns(&images).unwrap();
        assert_eq!(dims, (2, 8, 8));
        let cfg = enc.config();
        let mean = Tensor::new(&cfg.pixel_mean, &Device::Cpu).unwrap();
        let std = Tensor::new(&cfg.pixel_std, &Device::Cpu).unwrap();
        let nhwc = images
            .to_dtype(DType::F32)
            .unwrap()
            .permute((0, 2, 3, 1))
            .unwrap()
            .affine(1.0 / 255.0, 0.0)
            .unwrap()
            .broadcast_sub(&mean)
            .unwrap()
            .broadcast_div(&std)
            .unwrap()
            .contiguous()
            .unwrap();
        let expected = nhwc.apply_op1(Im2Col(Window { kernel: 4, stride: 4, padding: 0 })).unwrap();
        let diff = (cols - expected).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(diff < 1e-5, "{diff}");
    }

    fn small_config() -> ImageEncoderConfig {
        ImageEncoderConfig {
            image_size: 32,
            patch_size: 4,
            out_channels: 6,
            widths: vec![8, 12],
            blocks: vec![1, 1],
            ..Default::default()
        }
    }

    fn random_images(n: usize, size: usize, seed: u64) -> Tensor {
        let mut s = seed;
        let data: Vec<u8> = (0..n * 3 * size * size)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 56) as u8
            })
            .collect();
        Tensor::from_vec(data, (n, 3, size, size), &Device::Cpu).unwrap()
    }

    #[test]
    fn output_shape_and_input_checks() {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let enc = ImageEncoder::new(small_config(), vb).unwrap();
        let y = enc.forward(&random_images(3, 32, 1)).unwrap();
        assert_eq!(y.dims(), &[3, 6, 8, 8]);
        assert_eq!(y.dtype(), DType::F32);
        let y_last = enc.forward_channels_last(&random_images(3, 32, 1)).unwrap();
        assert_eq!(y_last.dims(), &[3, 8, 8, 6]);
        let diff = (y_last.permute((0, 3, 1, 2)).unwrap() - &y).unwrap().abs().unwrap().sum_all().unwrap();
        assert_eq!(diff.to_scalar::<f32>().unwrap(), 0.0);
        let wrong_size = random_images(1, 16, 1);
        assert!(matches!(enc.forward(&wrong_size), Err(PolicyError::Invalid(_))));
        let wrong_dtype = random_images(1, 32, 1).to_dtype(DType::F32).unwrap();
        assert!(matches!(enc.forward(&wrong_dtype), Err(PolicyError::Invalid(_))));
        let bad = ImageEncoderConfig { image_size: 36, ..small_config() };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn weights_use_pytorch_layouts_and_names() {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        ImageEncoder::new(ImageEncoderConfig::default(), vb).unwrap();
        let data = varmap.data().lock().unwrap();
        assert_eq!(data["stem.weight"].dims(), &[32, 3, 4, 4]);
        assert_eq!(data["levels.1.down.weight"].dims(), &[96, 32, 2, 2]);
        assert_eq!(data["levels.2.blocks.0.conv1.weight"].dims(), &[128, 128, 3, 3]);
        assert_eq!(data["heads.0.proj.weight"].dims(), &[120, 32, 1, 1]);
        assert_eq!(data["heads.2.proj.weight"].dims(), &[120, 128, 1, 1]);
        assert_eq!(data["heads.1.norm.weight"].dims(), &[96]);
    }

    #[test]
    fn gradients_match_finite_differences() {
        // f64 weights; the loss is a fixed random projection of the features.
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F64, &dev);
        let enc = ImageEncoder::new(small_config(), vb).unwrap();
        // Make the zero-initialised convs non-zero so every path carries gradient.
        for (name, var) in varmap.data().lock().unwrap().iter() {
            if name.ends_with("conv2.weight") {
                var.set(&Tensor::randn(0f64, 0.1, var.shape(), &dev).unwrap()).unwrap();
            }
        }
        let images = random_images(2, 32, 3);
        let proj = Tensor::randn(0f64, 1.0, (2, 6, 8, 8), &dev).unwrap();
        let loss =
            |enc: &ImageEncoder| -> Tensor { (enc.forward(&images).unwrap() * &proj).unwrap().sum_all().unwrap() };
        let grads = loss(&enc).backward().unwrap();
        let data = varmap.data().lock().unwrap().clone();
        for name in [
            "stem.weight",
            "levels.0.blocks.0.conv1.weight",
            "levels.0.blocks.0.norm2.weight",
            "levels.1.down.weight",
            "levels.1.blocks.0.conv2.weight",
            "heads.1.proj.bias",
            "heads.1.norm.bias",
            "heads.0.proj.weight",
        ] {
            let var = &data[name];
            let g = values(grads.get(var).unwrap_or_else(|| panic!("no gradient for {name}")));
            let base = values(var.as_tensor());
            for idx in [0usize, base.len() / 2, base.len() - 1] {
                let eps = 1e-5;
                let mut plus = base.clone();
                plus[idx] += eps;
                var.set(&Tensor::from_vec(plus, var.shape(), &dev).unwrap()).unwrap();
                let lp = loss(&enc).to_scalar::<f64>().unwrap();
                let mut minus = base.clone();
                minus[idx] -= eps;
                var.set(&Tensor::from_vec(minus, var.shape(), &dev).unwrap()).unwrap();
                let lm = loss(&enc).to_scalar::<f64>().unwrap();
                var.set(&Tensor::from_vec(base.clone(), var.shape(), &dev).unwrap()).unwrap();
                let numeric = (lp - lm) / (2.0 * eps);
                let tol = 1e-6 * numeric.abs().max(1.0);
                assert!((numeric - g[idx]).abs() < tol, "{name}[{idx}]: autodiff {} vs numeric {numeric}", g[idx]);
            }
        }
    }

    #[test]
    fn encoder_learns_a_per_pixel_colour_task() {
        // Features must predict each output pixel's mean red value: a quick
        // end-to-end check that forward, backward and AdamW fit together.
        use crate::policy::training::adamw::{AdamW, AdamWConfig};
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let enc = ImageEncoder::new(small_config(), vb.pp("encoder")).unwrap();
        let readout = candle_nn::linear(6, 1, vb.pp("readout")).unwrap();
        let mut opt = AdamW::new(&varmap, AdamWConfig { learning_rate: 3e-3, ..Default::default() }).unwrap();
        let images = random_images(4, 32, 9);
        // Target: red channel averaged over 4x4 patches, in [0, 1].
        let target = images
            .to_dtype(DType::F32)
            .unwrap()
            .narrow(1, 0, 1)
            .unwrap()
            .avg_pool2d(4)
            .unwrap()
            .affine(1.0 / 255.0, 0.0)
            .unwrap()
            .permute((0, 2, 3, 1))
            .unwrap();
        let mut first = None;
        let mut last = 0.0;
        for _ in 0..60 {
            let feats = enc.forward_channels_last(&images).unwrap();
            let pred = candle_nn::Module::forward(&readout, &feats).unwrap();
            let loss = (pred - &target).unwrap().sqr().unwrap().mean_all().unwrap();
            last = loss.to_scalar::<f32>().unwrap();
            first.get_or_insert(last);
            opt.backward_step(&loss).unwrap();
        }
        let first = first.unwrap();
        assert!(last < 0.1 * first, "loss {first} -> {last}");
    }
}
