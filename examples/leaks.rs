//! Counts leaks at scale: traces 10 million lines through closed sample scenes and reports
//! lines with an odd number of crossings, lines whose crossings do not alternate sides, and
//! segments the tallies send to the sky, absorb or darken at a contact (all should be 0 in the
//! furnace; the level's non-alternating lines are contacts, such as the door against the wall).
//!
//!     cargo run --release --example leaks

use radiosity::bake::Bake;
use radiosity::loader::{LoadOptions, load};
use radiosity::solve::tally::ABSORBED;
use radiosity::timeline::LineParams;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for name in ["scenes/furnace.gltf", "scenes/level.gltf"] {
        let options = LoadOptions {
            start: Some(0.0),
            end: Some(0.0),
            ..LoadOptions::default()
        };
        let scene = load(&std::fs::read(name)?, &options)?;
        let bake = Bake::trace(
            scene,
            &LineParams {
                lines: 10_000_000,
                seed: 1,
            },
        )?;
        let list = bake.list();
        let odd = (0..list.lines())
            .filter(|&l| list.static_hits(l).len() % 2 == 1)
            .count();
        let unordered = (0..list.lines())
            .filter(|&l| {
                list.static_hits(l)
                    .windows(2)
                    .any(|w| w[0].front() == w[1].front())
            })
            .count();
        let t = bake.frame_tally(0);
        let lost: u64 = (0..t.patches())
            .flat_map(|i| {
                let (columns, counts) = t.row(i);
                columns.iter().zip(counts)
            })
            .filter(|&(&j, _)| j >= ABSORBED)
            .map(|(_, &c)| u64::from(c))
            .sum();
        println!(
            "{name}: {} lines, {odd} odd, {unordered} not alternating, {lost} segments to the sky, absorbed or at a contact",
            list.lines()
        );
    }
    Ok(())
}
