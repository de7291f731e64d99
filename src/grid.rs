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

    /// The row-major values, taken out of the grid.
    pub fn into_data(self) -> Vec<T> {
        self.data
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

impl<T: Copy + Send + Sync> Grid<T> {
    /// The part of the grid inside `win` (which must lie within it), copied in parallel.
    ///
    /// # Panics
    /// When `win` reaches outside the grid.
    pub(crate) fn crop(&self, win: Window) -> Grid<T> {
        use rayon::prelude::*;
        assert!(
            win.x1 <= self.width && win.y1 <= self.height,
            "window {win} outside a {}×{} grid",
            self.width,
            self.height
        );
        let (w, h) = (win.width(), win.height());
        let Some(&first) = self
            .data
            .get(win.y0 * self.width + win.x0)
            .filter(|_| w * h > 0)
        else {
            return Grid {
                width: w,
                height: h,
                data: Vec::new(),
            };
        };
        let mut data = vec![first; w * h];
        data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let from = (win.y0 + y) * self.width + win.x0;
            row.copy_from_slice(&self.data[from..from + w]);
        });
        Grid {
            width: w,
            height: h,
            data,
        }
    }

    /// The rows of the grid inside `win` (which must lie within it), each cut to the window's
    /// columns, for writing in parallel: (row index within the window, its cells).
    ///
    /// # Panics
    /// When `win` reaches outside the grid.
    pub(crate) fn par_window_rows_mut(
        &mut self,
        win: Window,
    ) -> impl rayon::iter::IndexedParallelIterator<Item = (usize, &mut [T])> {
        use rayon::prelude::*;
        assert!(
            win.x1 <= self.width && win.y1 <= self.height,
            "window {win} outside a {}×{} grid",
            self.width,
            self.height
        );
        let width = self.width.max(1);
        self.data
            .par_chunks_mut(width)
            .skip(win.y0)
            .take(win.height())
            .map(move |row| &mut row[win.x0..win.x1])
            .enumerate()
    }
}

impl Grid<bool> {
    /// Number of `true` pixels.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&b| b).count()
    }

    /// The smallest window holding every `true` pixel; `None` for an empty mask.
    pub fn bounding_box(&self) -> Option<Window> {
        let w = self.width.max(1);
        let y0 = self.data.iter().position(|&v| v)? / w;
        let y1 = self.data.iter().rposition(|&v| v)? / w + 1;
        let (mut x0, mut x1) = (self.width, 0);
        for row in self.data[y0 * w..y1 * w].chunks_exact(w) {
            if let Some(first) = row.iter().position(|&v| v) {
                x0 = x0.min(first);
                x1 = x1.max(row.iter().rposition(|&v| v).unwrap_or(first) + 1);
            }
        }
        Some(Window { x0, y0, x1, y1 })
    }
}

/// The 4-neighbours of pixel `p` (row-major) of a `w`×`h` grid, in the order left, right,
/// above, below; `None` where a neighbour would lie outside the grid.
pub(crate) fn four_neighbours(p: usize, w: usize, h: usize) -> [Option<usize>; 4] {
    let (x, y) = (p % w, p / w);
    [
        (x > 0).then(|| p - 1),
        (x + 1 < w).then(|| p + 1),
        (y > 0).then(|| p - w),
        (y + 1 < h).then(|| p + w),
    ]
}

/// An axis-aligned rectangle of pixels: columns `x0..x1`, rows `y0..y1` (ends excluded).
///
/// An [`crate::capture::stack::ImageStack`] stores only the window its mask spans; pixel indices stay
/// those of the whole image (`y * width + x`) and [`Window::local`] maps them into the window.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
pub struct Window {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
}

impl Window {
    /// The whole of a `width`×`height` image.
    pub fn full(width: usize, height: usize) -> Self {
        Window {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        }
    }

    /// Columns in the window.
    pub fn width(&self) -> usize {
        self.x1.saturating_sub(self.x0)
    }

    /// Rows in the window.
    pub fn height(&self) -> usize {
        self.y1.saturating_sub(self.y0)
    }

    /// Pixels in the window.
    pub fn len(&self) -> usize {
        self.width() * self.height()
    }

    /// Whether the window holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The window cut to a `width`×`height` image (empty when it lies outside).
    pub fn clamp(&self, width: usize, height: usize) -> Self {
        let (x1, y1) = (self.x1.min(width), self.y1.min(height));
        Window {
            x0: self.x0.min(x1),
            y0: self.y0.min(y1),
            x1,
            y1,
        }
    }

    /// Whether pixel `(x, y)` lies inside.
    pub fn contains(&self, x: usize, y: usize) -> bool {
        (self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)
    }

    /// Whether `other` lies entirely inside this window.
    pub fn covers(&self, other: &Window) -> bool {
        other.is_empty()
            || (self.x0 <= other.x0
                && other.x1 <= self.x1
                && self.y0 <= other.y0
                && other.y1 <= self.y1)
    }

    /// Index inside the window (row-major, [`Window::width`] wide) of pixel `pixel` of an
    /// image `image_width` wide; `None` outside the window.
    pub fn local(&self, image_width: usize, pixel: usize) -> Option<usize> {
        let w = image_width.max(1);
        let (x, y) = (pixel % w, pixel / w);
        self.contains(x, y)
            .then(|| (y - self.y0) * self.width() + (x - self.x0))
    }
}

impl std::fmt::Display for Window {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "columns {}..{}, rows {}..{}",
            self.x0, self.x1, self.y0, self.y1
        )
    }
}
