//! The `harmonize` command.
fn main() {
    println!("harmonize {}", harmonizer_core::VERSION);
}
