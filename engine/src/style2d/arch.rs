//! The VGG variants the encoder supports, described up to relu4_1: which 3×3 convolutions
//! there are, their channel counts, where the 2×2 max-pools sit, and which ReLU outputs are
//! exposed to AdaIN and the losses. The decoder is built as the mirror of the same list.

use serde::{Deserialize, Serialize};

/// One 3×3 convolution of the encoder (reflection padding 1, stride 1, followed by ReLU).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvSpec {
    /// Caffe-style name, e.g. `conv3_1`; also the tensor-name prefix in the project's layout.
    pub name: &'static str,
    pub c_in: usize,
    pub c_out: usize,
    /// A 2×2 max-pool (stride 2) precedes this convolution.
    pub pool_before: bool,
    /// The ReLU after this convolution is one of the exposed features (relu1_1 … relu4_1).
    pub tap: bool,
}

const fn conv(
    name: &'static str,
    c_in: usize,
    c_out: usize,
    pool_before: bool,
    tap: bool,
) -> ConvSpec {
    ConvSpec {
        name,
        c_in,
        c_out,
        pool_before,
        tap,
    }
}

const VGG16: [ConvSpec; 8] = [
    conv("conv1_1", 3, 64, false, true),
    conv("conv1_2", 64, 64, false, false),
    conv("conv2_1", 64, 128, true, true),
    conv("conv2_2", 128, 128, false, false),
    conv("conv3_1", 128, 256, true, true),
    conv("conv3_2", 256, 256, false, false),
    conv("conv3_3", 256, 256, false, false),
    conv("conv4_1", 256, 512, true, true),
];

const VGG19: [ConvSpec; 9] = [
    conv("conv1_1", 3, 64, false, true),
    conv("conv1_2", 64, 64, false, false),
    conv("conv2_1", 64, 128, true, true),
    conv("conv2_2", 128, 128, false, false),
    conv("conv3_1", 128, 256, true, true),
    conv("conv3_2", 256, 256, false, false),
    conv("conv3_3", 256, 256, false, false),
    conv("conv3_4", 256, 256, false, false),
    conv("conv4_1", 256, 512, true, true),
];

/// A VGG network truncated after relu4_1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VggArch {
    Vgg16,
    Vgg19,
}

impl VggArch {
    /// The convolutions from conv1_1 to conv4_1, in order.
    pub fn convs(self) -> &'static [ConvSpec] {
        match self {
            VggArch::Vgg16 => &VGG16,
            VggArch::Vgg19 => &VGG19,
        }
    }

    /// Channels of the deepest feature (relu4_1).
    pub const FEATURE_CHANNELS: usize = 512;

    /// Total downsampling factor at relu4_1: image sides must be multiples of it.
    pub const STRIDE: usize = 8;

    pub fn name(self) -> &'static str {
        match self {
            VggArch::Vgg16 => "vgg16",
            VggArch::Vgg19 => "vgg19",
        }
    }

    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "vgg16" => Some(VggArch::Vgg16),
            "vgg19" => Some(VggArch::Vgg19),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn channel_chains_are_consistent() {
        for arch in [VggArch::Vgg16, VggArch::Vgg19] {
            let convs = arch.convs();
            assert_eq!(convs[0].c_in, 3);
            for pair in convs.windows(2) {
                assert_eq!(pair[0].c_out, pair[1].c_in, "{}", pair[1].name);
            }
            assert_eq!(convs.last().unwrap().c_out, VggArch::FEATURE_CHANNELS);
            assert_eq!(convs.iter().filter(|c| c.tap).count(), 4);
            assert_eq!(convs.iter().filter(|c| c.pool_before).count(), 3);
        }
    }
}
