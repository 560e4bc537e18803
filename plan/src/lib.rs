//! The catalogue the other crates stand on: the [`Stage`]s of a job and what each reads, the
//! [`Preset`]s, and the `stage.key=value` override syntax with the bounds of every setting.
//! It knows no candle and no network, so the coordinator (which links no engine), the worker,
//! the engine and the CLI all read the same list. It also holds the parsers of user files that
//! the coordinator and the engine share ([`npy`], [`device`] names), and the dataset formats
//! with the one rule that finds a scene in an upload ([`scene_format`]).
//!
//! Adding a stage starts here: a [`Stage`] variant with its name, upstream stages, inputs and
//! default memory, and its bounds in [`bounds`]; `docs/ARCHITECTURE.md` lists the rest.

pub mod bounds;
pub mod device;
pub mod npy;
pub mod preset;
pub mod scene_format;
pub mod settings;
pub mod stage;

pub use preset::Preset;
pub use scene_format::{find_scene, DatasetFacts, SceneFormat};
pub use settings::{Override, SettingError};
pub use stage::{Source, Stage, StageInputs};
