//! `--plot FIG.svg`: every estimate against time, one panel per parameter (`a0`, `a1`, `b0`, each relative to its
//! truth when the input has one, else in its units), with the truth as a dashed line.

use crate::cmd::identify::Identified;
use crate::cmd::CliError;
use plotters::prelude::*;

/// Reads one parameter.
type Getter = fn(&nanopos_id::StageParams<f64>) -> f64;

const COLOURS: [RGBColor; 4] =
    [RGBColor(31, 119, 180), RGBColor(214, 39, 40), RGBColor(44, 160, 44), RGBColor(148, 103, 189)];

/// Render `r` as SVG text.
pub fn svg(r: &Identified) -> Result<String, String> {
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, (900, 900)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let panels = root.split_evenly((3, 1));
        let getters: [(&str, Getter); 3] =
            [("a0 (1/s^2)", |p| p.a0), ("a1 (1/s)", |p| p.a1), ("b0 (um/s^2 V)", |p| p.b0)];
        let t_max = r.times.last().copied().unwrap_or(1.0);
        let t_min = r.times.first().copied().unwrap_or(0.0);
        for (panel, (label, get)) in panels.iter().zip(getters) {
            // Relative to the truth when known (the interesting scale is per cent), else absolute.
            let relative = r.truth.is_some();
            let value = |i: usize, p: &nanopos_id::StageParams<f64>| match &r.truth {
                Some(tr) => 100.0 * (get(p) / get(&tr[i]) - 1.0),
                None => get(p),
            };
            let mut lo = f64::INFINITY;
            let mut hi = f64::NEG_INFINITY;
            for (i, row) in r.estimates.iter().enumerate() {
                for p in row {
                    let v = value(i, p);
                    if v.is_finite() {
                        lo = lo.min(v);
                        hi = hi.max(v);
                    }
                }
            }
            if relative && lo.max(-20.0) < hi.min(20.0) {
                // Show +-20 % at most: the start from the initial guess would otherwise flatten the rest. Unless no
                // estimate is within it (held away from the truth: a record without excitation): then their range.
                (lo, hi) = (lo.max(-20.0), hi.min(20.0));
            }
            if lo >= hi {
                // One value, or none finite (a truth of 0).
                (lo, hi) = if lo.is_finite() { (lo - 1.0, hi + 1.0) } else { (-1.0, 1.0) };
            }
            let caption = if relative { format!("{label}: error against the truth, %") } else { label.to_string() };
            let mut chart = ChartBuilder::on(panel)
                .caption(caption, ("sans-serif", 16))
                .margin(8)
                .x_label_area_size(30)
                .y_label_area_size(70)
                .build_cartesian_2d(t_min..t_max, lo..hi)
                .map_err(|e| e.to_string())?;
            chart.configure_mesh().x_desc("t (s)").draw().map_err(|e| e.to_string())?;
            // At most ~2000 points per series: plenty for 900 pixels, and a file of a few hundred kB.
            let stride = (r.times.len() / 2000).max(1);
            for (col, name) in r.names.iter().enumerate() {
                let colour = COLOURS[col % COLOURS.len()];
                let points = r
                    .times
                    .iter()
                    .enumerate()
                    .step_by(stride)
                    .map(|(i, &t)| (t, value(i, &r.estimates[i][col]).clamp(lo, hi)));
                chart
                    .draw_series(LineSeries::new(points, colour))
                    .map_err(|e| e.to_string())?
                    .label(*name)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour));
            }
            if r.truth.is_some() {
                let zero = r.times.iter().map(|&t| (t, 0.0));
                chart
                    .draw_series(DashedLineSeries::new(zero, 6, 4, BLACK.into()))
                    .map_err(|e| e.to_string())?
                    .label("truth")
                    .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| e.to_string())?;
        }
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(text)
}

/// Refuse a plot file named for another image format (`fig.png` would have held SVG text that no PNG viewer opens); a
/// name without an extension (`/dev/stdout`) is taken.
pub fn check_name(path: &std::path::Path) -> Result<(), CliError> {
    match path.extension().map(|e| e.to_string_lossy()) {
        Some(ext) if !ext.eq_ignore_ascii_case("svg") => Err(CliError(format!(
            "--plot {}: the plot is SVG: name it .svg (an image viewer would not open SVG text in a .{ext} file; a \
             browser opens the .svg, and e.g. `rsvg-convert fig.svg -o fig.png` converts it)",
            path.display()
        ))),
        _ => Ok(()),
    }
}

/// Write the plot through an [`crate::cmd::OutputFile`] (prepared, not yet committed).
pub fn write(mut f: crate::cmd::OutputFile, r: &Identified) -> Result<crate::cmd::OutputFile, CliError> {
    let text = svg(r).map_err(|e| CliError(format!("{}: cannot draw: {e}", f.path().display())))?;
    std::io::Write::write_all(f.writer(), text.as_bytes()).map_err(|e| f.write_error(e))?;
    Ok(f)
}
