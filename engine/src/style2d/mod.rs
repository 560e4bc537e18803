//! The 2D stylization network (AdaIN): a frozen pretrained VGG encoder up to relu4_1, the
//! AdaIN layer, a trainable mirror decoder, the content/style losses, and a VAE over style
//! features. Everything is composed from candle ops whose backward passes are verified by
//! finite differences (see the tests of each module).

pub mod arch;
pub mod frozen_conv;
pub mod pad;
pub mod resample;
pub mod weights;

pub mod adain;
pub mod decoder;
pub mod encoder;
#[cfg(test)]
pub(crate) mod gradcheck;
pub mod losses;
pub mod st_file;
