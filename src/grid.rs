//! Row-major 2-D grids: the image, mask and map container used by every stage.
//!
//! Pixel `(x, y)` is column `x` and row `y`, row 0 at the top; element `y * width + x`.

use crate::error::{Error, Result};
use nalgebra::Vector3;

/// A row-major 2-D array of `T`.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid<T> {
    width: usize,
    height: usize,
    data: Vec<T>,
}

/// Which pixels belong to the object (`true`) and which do not.
pub type Mask = Grid<bool>;
/// One float per pixel: depth, albedo, residual, curl…; NaN where undefined.
pub type ScalarMap = Grid<f32>;
/// One unit vector per pixel in the camera frame (x right, y up, z towards the camera);
/// NaN components where undefined.
pub type NormalMap = Grid<Vector3<f32>>;

impl<T: Clone> Grid<T> {
    /// A `width`×`height` grid filled with `value`.
    pub fn new(width: usize, height: usize, value: T) -> Self {
        Grid {
            width,
            height,
            data: vec![value; width * height],
        }
    }
}

impl<T> Grid<T> {
    /// Wraps row-major `data`.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] when `data.len() != width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Result<Self> {
        if data.len() != width * height {
            return Err(Error::param(
                "data",
                format!(
                    "{} values cannot fill a {width}x{height} grid ({} needed)",
                    data.len(),
                    width * height
                ),
            ));
        }
        Ok(Grid {
            width,
            height,
            data,
        })
    }

    /// Builds a grid by calling `f(x, y)` for every pixel.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> T) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Grid {
            width,
            height,
            data,
        }
    }

    /// Number of columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Number of rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True when the grid has no pixels.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The element at column `x`, row `y`.
    ///
    /// # Panics
    /// When `(x, y)` is outside the grid (a programming error, not a data error).
    pub fn at(&self, x: usize, y: usize) -> &T {
        &self.data[y * self.width + x]
    }

    /// Mutable element at column `x`, row `y`.
    ///
    /// # Panics
    /// When `(x, y)` is outside the grid.
    pub fn at_mut(&mut self, x: usize, y: usize) -> &mut T {
        &mut self.data[y * self.width + x]
    }

    /// The elements in row-major order.
    pub fn data(&self) -> &[T] {
        &self.data
    }

    /// Mutable elements in row-major order.
    pub fn data_mut(&mut self) -> &mut [T] {
        &mut self.data
    }

    /// Consumes the grid, returning its row-major elements.
    pub fn into_vec(self) -> Vec<T> {
        self.data
    }

    /// Applies `f` to every element.
    pub fn map<U>(&self, f: impl FnMut(&T) -> U) -> Grid<U> {
        Grid {
            width: self.width,
            height: self.height,
            data: self.data.iter().map(f).collect(),
        }
    }

    /// True when `other` has the same width and height.
    pub fn same_size<U>(&self, other: &Grid<U>) -> bool {
        self.width == other.width && self.height == other.height
    }

    /// Checks that `other` has this grid's size.
    ///
    /// # Errors
    /// [`Error::DimensionMismatch`] naming `what` otherwise.
    pub fn check_same_size<U>(&self, other: &Grid<U>, what: &str) -> Result<()> {
        if self.same_size(other) {
            Ok(())
        } else {
            Err(Error::DimensionMismatch {
                what: what.to_string(),
                width: self.width,
                height: self.height,
                found_width: other.width,
                found_height: other.height,
            })
        }
    }
}

impl Grid<bool> {
    /// Number of `true` pixels.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&b| b).count()
    }

    /// The rows holding `true` pixels, as `(first, last + 1)`; `None` for an empty mask.
    pub fn row_span(&self) -> Option<(usize, usize)> {
        let w = self.width.max(1);
        let first = self.data.iter().position(|&v| v)? / w;
        let last = self.data.iter().rposition(|&v| v)? / w;
        Some((first, last + 1))
    }
}
