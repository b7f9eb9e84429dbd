//! The `shocktwin` binary: parses arguments and dispatches.
fn main() {
    println!("shocktwin: not yet");
}
