//! What draws and colours, above the files: the colour rules every renderer shares
//! ([`color`]), how a view is drawn and what it gives ([`settings`]), batch files drawn and
//! resolved ([`batch`]), a store's selected nodes coloured and drawn ([`lod`]), and raw LAS/LAZ
//! points loaded with the payload their colour mode needs for the progressive renderers
//! ([`raw`]). mortar-io hands over what it reads (a batch file's batches in
//! [`mortar_io::batch_input`], a store's LOD structure and payloads in
//! [`mortar_io::store::StoreLod`]); everything here runs during a frame.

pub mod batch;
pub mod color;
pub mod lod;
pub mod raw;
pub mod settings;

pub use color::ColorChoice;
pub use settings::{RenderSettings, Rendered};
