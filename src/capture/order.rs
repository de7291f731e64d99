//! The order of a capture's images, and the trap of numbered file names sorted as text.
//!
//! Lights given as a plain list (one direction per line, or JSON entries that name no file)
//! are paired with the images by position. A shell expands `cat.*.png` in text order, so
//! `cat.10.png` comes before `cat.2.png`; with a plain list written in capture order, most
//! images get another image's light. Nothing in the numbers shows it: the solve still fits,
//! only less well (DiLiGenT cat renamed `cat.1.png` … `cat.96.png` with its plain
//! `light_directions.txt`: normals 25.4° off those of the right pairing), so the mistake must
//! be caught from the names.
//!
//! [`text_sorted_numbering`] finds it: the images are in exactly the order a text sort gives,
//! and that order differs from the natural one (digit runs compared as numbers). An order
//! chosen by hand (an image list, or names typed one by one) is never text-sorted by chance
//! in a way that differs from the natural order, unless it was meant to be; then
//! [`ImageOrder::AsGiven`] keeps it. Zero-padded names (`001.png`) sort the same both ways
//! and are never flagged. Lights that name their image are matched by name and are unaffected.

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

/// How the images given to [`crate::capture::CaptureFiles::from_files_ordered`] are ordered
/// before they are paired with a plain list of lights.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ImageOrder {
    /// Keep the order given, but refuse numbered names in text order that differs from the
    /// numeric order ([`crate::Error::ImageOrder`]).
    #[default]
    Checked,
    /// Sort the images by their names, digit runs compared as numbers (`2` before `10`).
    Natural,
    /// Keep the order given, whatever it is.
    AsGiven,
}

/// Compares two paths with digit runs taken as numbers (`cat.2.png` < `cat.10.png`); other
/// characters compare as text. Equal numbers with different zero padding fall back to the
/// text order, so the comparison is total.
pub fn natural_cmp(a: &Path, b: &Path) -> Ordering {
    let (a, b) = (a.to_string_lossy(), b.to_string_lossy());
    let (mut x, mut y) = (a.as_bytes(), b.as_bytes());
    while let (Some(&c), Some(&d)) = (x.first(), y.first()) {
        if c.is_ascii_digit() && d.is_ascii_digit() {
            let n = x.iter().take_while(|u| u.is_ascii_digit()).count();
            let m = y.iter().take_while(|u| u.is_ascii_digit()).count();
            let (p, q) = (&x[..n], &y[..m]);
            // Numbers of any length: strip leading zeros, then longer is larger.
            let trim = |s: &[u8]| -> usize { s.iter().take_while(|&&u| u == b'0').count() };
            let (p0, q0) = (&p[trim(p)..], &q[trim(q)..]);
            let by_value = p0.len().cmp(&q0.len()).then_with(|| p0.cmp(q0));
            if by_value != Ordering::Equal {
                return by_value;
            }
            (x, y) = (&x[n..], &y[m..]);
        } else {
            if c != d {
                return c.cmp(&d);
            }
            (x, y) = (&x[1..], &y[1..]);
        }
    }
    x.len().cmp(&y.len()).then_with(|| a.cmp(&b))
}

/// The images in natural order ([`natural_cmp`]).
pub fn natural_order(images: &[PathBuf]) -> Vec<PathBuf> {
    let mut sorted = images.to_vec();
    sorted.sort_by(|a, b| natural_cmp(a, b));
    sorted
}

/// When `images` are in text order and that differs from their natural order — what a shell
/// glob does to `name.1.png … name.12.png` — returns the first pair out of natural order
/// (`(earlier, later)`: `earlier` is given first but numbered higher) and the images in
/// natural order; otherwise `None`.
pub fn text_sorted_numbering(images: &[PathBuf]) -> Option<(PathBuf, PathBuf, Vec<PathBuf>)> {
    let text_sorted = images
        .windows(2)
        .all(|w| w[0].as_os_str() <= w[1].as_os_str());
    if !text_sorted {
        return None;
    }
    let pair = images
        .windows(2)
        .find(|w| natural_cmp(&w[0], &w[1]) == Ordering::Greater)?;
    Some((pair[0].clone(), pair[1].clone(), natural_order(images)))
}

/// Puts `images` in the order `order` asks for.
///
/// # Errors
/// [`crate::Error::ImageOrder`] under [`ImageOrder::Checked`] when the images are numbered
/// and in text order that differs from their numeric order; the error holds the corrected
/// order.
pub fn apply(images: &[PathBuf], order: ImageOrder) -> crate::Result<Vec<PathBuf>> {
    match order {
        ImageOrder::AsGiven => Ok(images.to_vec()),
        ImageOrder::Natural => Ok(natural_order(images)),
        ImageOrder::Checked => match text_sorted_numbering(images) {
            None => Ok(images.to_vec()),
            Some((earlier, later, natural)) => Err(crate::Error::ImageOrder {
                earlier,
                later,
                natural,
            }),
        },
    }
}

/// Names of up to `max` paths, `…` for the rest: for messages.
pub(crate) fn short_list(paths: &[PathBuf], max: usize) -> String {
    let mut names: Vec<String> = paths
        .iter()
        .take(max)
        .map(|p| {
            p.file_name()
                .map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into())
        })
        .collect();
    if paths.len() > max {
        names.push(format!("… ({} in all)", paths.len()));
    }
    names.join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paths(names: &[&str]) -> Vec<PathBuf> {
        names.iter().map(PathBuf::from).collect()
    }

    #[test]
    fn digit_runs_compare_as_numbers() {
        let cmp = |a: &str, b: &str| natural_cmp(Path::new(a), Path::new(b));
        assert_eq!(cmp("cat.2.png", "cat.10.png"), Ordering::Less);
        assert_eq!(cmp("cat.10.png", "cat.9.png"), Ordering::Greater);
        assert_eq!(cmp("a/img_007.tif", "a/img_10.tif"), Ordering::Less);
        assert_eq!(cmp("b2c3", "b2c12"), Ordering::Less);
        assert_eq!(cmp("x.png", "x.png"), Ordering::Equal);
        // Same value, different padding: still a strict order.
        assert_ne!(cmp("a01", "a1"), Ordering::Equal);
        assert_eq!(
            cmp("a99999999999999999999999", "a100000000000000000000000"),
            Ordering::Less
        );
    }

    #[test]
    fn shell_order_of_a_numbered_sequence_is_caught() {
        // What `cat.[0-9]*.png` expands to for cat.1 … cat.12.
        let mut shell: Vec<String> = (1..=12).map(|k| format!("cat.{k}.png")).collect();
        shell.sort();
        let shell = paths(&shell.iter().map(String::as_str).collect::<Vec<_>>());
        let (earlier, later, natural) = text_sorted_numbering(&shell).unwrap();
        assert_eq!(earlier, PathBuf::from("cat.12.png"));
        assert_eq!(later, PathBuf::from("cat.2.png"));
        let expected: Vec<PathBuf> = (1..=12).map(|k| format!("cat.{k}.png").into()).collect();
        assert_eq!(natural, expected);
        match apply(&shell, ImageOrder::Checked).unwrap_err() {
            crate::Error::ImageOrder { natural, .. } => assert_eq!(natural, expected),
            e => panic!("{e}"),
        }
        assert_eq!(apply(&shell, ImageOrder::Natural).unwrap(), expected);
        assert_eq!(apply(&shell, ImageOrder::AsGiven).unwrap(), shell);
    }

    #[test]
    fn orders_that_mean_what_they_say_pass() {
        // Zero-padded names sort the same as text and as numbers.
        let padded: Vec<PathBuf> = (1..=96).map(|k| format!("{k:03}.png").into()).collect();
        assert!(text_sorted_numbering(&padded).is_none());
        // Natural order as an image list gives it (10 after 9: not text-sorted).
        let listed: Vec<PathBuf> = (0..12).map(|k| format!("buddha.{k}.png").into()).collect();
        assert!(text_sorted_numbering(&listed).is_none());
        assert_eq!(apply(&listed, ImageOrder::Checked).unwrap(), listed);
        // Names without numbers, and fewer than ten numbered images.
        assert!(text_sorted_numbering(&paths(&["left.png", "right.png", "top.png"])).is_none());
        let few: Vec<PathBuf> = (1..=9).map(|k| format!("i{k}.png").into()).collect();
        assert!(text_sorted_numbering(&few).is_none());
        // A hand-made order that is not text-sorted is kept.
        let hand = paths(&["img.3.png", "img.1.png", "img.2.png"]);
        assert_eq!(apply(&hand, ImageOrder::Checked).unwrap(), hand);
    }

    #[test]
    fn messages_list_a_few_names() {
        let many: Vec<PathBuf> = (1..=20).map(|k| format!("d/i{k}.png").into()).collect();
        assert_eq!(short_list(&many[..2], 4), "i1.png i2.png");
        assert_eq!(short_list(&many, 3), "i1.png i2.png i3.png … (20 in all)");
    }
}
