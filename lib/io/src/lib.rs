//! mortar-io
