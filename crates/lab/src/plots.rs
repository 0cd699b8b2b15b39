//! PNG plots of an evaluation: ROC curves per horizon, the reliability
//! diagram, and the training curves stored in the model file.
//!
//! Text is drawn with DejaVu Sans (assets/, Bitstream Vera licence), embedded
//! so that plots render on machines without fonts.

use std::path::Path;
use std::sync::Once;

use plotters::prelude::*;

use super::metrics::{reliability, roc_curve};
use fall_guard_runtime::model::EpochRecord;

static FONT: Once = Once::new();
const FONT_BYTES: &[u8] = include_bytes!("../../../assets/DejaVuSans.ttf");

fn register_font() {
    FONT.call_once(|| {
        if plotters::style::register_font("sans-serif", FontStyle::Normal, FONT_BYTES).is_err() {
            tracing::warn!("embedded font could not be registered: plots will have no text");
        }
    });
}

/// Errors of plotting.
#[derive(Debug, thiserror::Error)]
#[error("plot {path}: {message}")]
pub struct PlotError {
    /// The file.
    pub path: String,
    /// What failed.
    pub message: String,
}

fn err(path: &Path) -> impl Fn(String) -> PlotError + '_ {
    move |message| PlotError {
        path: path.display().to_string(),
        message,
    }
}

/// One series per horizon: label, probabilities, labels.
pub type HorizonSeries<'a> = (String, &'a [f32], &'a [bool]);

/// ROC curves, one line per horizon.
pub fn roc_plot(path: &Path, series: &[HorizonSeries<'_>]) -> Result<(), PlotError> {
    let roc = UnitSquarePlot {
        caption: "ROC",
        x_desc: "false positive rate",
        y_desc: "true positive rate",
        points: false,
        legend: SeriesLabelPosition::LowerRight,
    };
    roc.draw(path, series, roc_curve)
}

/// Reliability diagram (15 bins), one line per horizon.
pub fn reliability_plot(path: &Path, series: &[HorizonSeries<'_>]) -> Result<(), PlotError> {
    let diagram = UnitSquarePlot {
        caption: "Reliability (15 bins)",
        x_desc: "mean predicted probability",
        y_desc: "fraction fallen",
        points: true,
        legend: SeriesLabelPosition::UpperLeft,
    };
    diagram.draw(path, series, |p, y| {
        reliability(p, y, 15)
            .iter()
            .map(|&(c, f, _)| (c, f))
            .collect()
    })
}

/// A plot on [0, 1] x [0, 1] with the diagonal and one curve per horizon.
struct UnitSquarePlot {
    caption: &'static str,
    x_desc: &'static str,
    y_desc: &'static str,
    /// Mark each point of a curve.
    points: bool,
    legend: SeriesLabelPosition,
}

impl UnitSquarePlot {
    fn draw(
        &self,
        path: &Path,
        series: &[HorizonSeries<'_>],
        curve: impl Fn(&[f32], &[bool]) -> Vec<(f64, f64)>,
    ) -> Result<(), PlotError> {
        register_font();
        let e = err(path);
        let root = BitMapBackend::new(path, (640, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(self.caption, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(0.0..1.0, 0.0..1.0)
            .map_err(|x| e(x.to_string()))?;
        chart
            .configure_mesh()
            .x_desc(self.x_desc)
            .y_desc(self.y_desc)
            .draw()
            .map_err(|x| e(x.to_string()))?;
        chart
            .draw_series(LineSeries::new(
                vec![(0.0, 0.0), (1.0, 1.0)],
                BLACK.mix(0.3),
            ))
            .map_err(|x| e(x.to_string()))?;
        for (i, (label, p, y)) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let pts = curve(p, y);
            chart
                .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
                .map_err(|x| e(x.to_string()))?
                .label(label.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            if self.points {
                chart
                    .draw_series(
                        pts.iter()
                            .map(|&(x, y)| Circle::new((x, y), 3, color.filled())),
                    )
                    .map_err(|x| e(x.to_string()))?;
            }
        }
        chart
            .configure_series_labels()
            .position(self.legend.clone())
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|x| e(x.to_string()))?;
        root.present().map_err(|x| e(x.to_string()))
    }
}

/// Training and validation loss and validation accuracy per epoch.
pub fn training_plot(path: &Path, history: &[EpochRecord]) -> Result<(), PlotError> {
    register_font();
    let e = err(path);
    let root = BitMapBackend::new(path, (720, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let max_epoch = history.iter().map(|h| h.epoch).max().unwrap_or(1).max(2) as f64;
    let max_loss = history
        .iter()
        .flat_map(|h| [h.train_loss, h.val_loss])
        .filter(|v| v.is_finite())
        .fold(1.0f64, f64::max);
    let mut chart = ChartBuilder::on(&root)
        .caption("Training", ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(1.0..max_epoch, 0.0..max_loss.max(1.0))
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("epoch")
        .y_desc("loss / accuracy")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    type Curve = (&'static str, RGBColor, fn(&EpochRecord) -> f64);
    let lines: [Curve; 3] = [
        ("train loss", BLUE, |h| h.train_loss),
        ("validation loss", RED, |h| h.val_loss),
        ("validation accuracy", GREEN, |h| h.val_accuracy),
    ];
    for (label, color, f) in lines {
        let pts: Vec<(f64, f64)> = history.iter().map(|h| (h.epoch as f64, f(h))).collect();
        chart
            .draw_series(LineSeries::new(pts, color.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?
            .label(label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}
