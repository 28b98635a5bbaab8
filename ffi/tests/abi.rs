//! Integration tests of libharmonizer: the header is current, and the built
//! cdylib, loaded with `libloading`, works through the C ABI.

mod abi {
    pub mod driver;
    pub mod header;
}
