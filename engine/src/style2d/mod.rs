//! The 2D stylization network (AdaIN): a frozen pretrained VGG encoder up to relu4_1, the
//! AdaIN layer, a trainable mirror decoder, the content/style losses, and a VAE over style
//! features. Everything is composed from candle ops whose backward passes are verified by
//! finite differences (see the tests of each module). Documentation: `docs/STYLE2D.md`.

pub mod adain;
pub mod arch;
pub mod conv;
pub mod corpus;
pub mod decoder;
pub mod encoder;
pub mod fit;
pub mod images;
pub mod losses;
pub mod network;
pub mod pad;
pub mod painted;
pub mod palette;
pub mod resample;
pub mod st_file;
pub mod style_features;
pub mod vae;
pub mod weights;

#[cfg(test)]
pub(crate) mod gradcheck;
