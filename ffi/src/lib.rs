//! libharmonizer: the C ABI.
