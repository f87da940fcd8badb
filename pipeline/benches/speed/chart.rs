//! The speed bench's picture: where one sample's time goes on one core, as a stacked bar
//! per drive (the libraries' own work first, then the pipeline's stages), with the
//! issue's target for that camera size marked.

use std::fmt::Write as _;

/// One bar: a drive's class-map sample on one core, ms per sample.
#[derive(Debug, Clone)]
pub struct Bar {
    /// The drive's label (`800×450`).
    pub name: String,
    /// Wall time per sample (the table's "ms/sample 1 core").
    pub total: f64,
    /// libzstd, libjpeg-turbo and PNG alone for the sample's decoding (the floor table),
    /// when measured.
    pub libraries: [Option<f64>; 3],
    /// Stage means: decode, sweeps, images, projection, superpixels, voxels+maps.
    pub stages: [f64; 6],
    /// The target for this camera size, if the project has one.
    pub target: Option<f64>,
}

/// Segment names and colours, in bar order.
const SEGMENTS: [(&str, &str); 9] = [
    ("zstd (libzstd alone)", "#4c72b0"),
    ("JPEG (libjpeg-turbo alone)", "#6f94cf"),
    ("PNG class maps (alone)", "#a6c0e6"),
    ("rest of decoding", "#c9d7ec"),
    ("voxels + kernel maps", "#dd8452"),
    ("images (resize, flip)", "#e8a878"),
    ("projection", "#f2c9a6"),
    ("sweeps + superpixels", "#c44e52"),
    ("other (unattributed)", "#cccccc"),
];

impl Bar {
    /// The segments' lengths in [`SEGMENTS`] order.
    fn segments(&self) -> [f64; 9] {
        let [decode, sweeps, images, projection, superpixels, voxels] = self.stages;
        let [zstd, jpeg, png] = self.libraries.map(|v| v.unwrap_or(0.0));
        let libraries = (zstd + jpeg + png).min(decode);
        // The libraries alone were timed in their own loops (hot caches): what the decode
        // stage takes beyond them is the rest of decoding. Scaled down if they exceed it.
        let scale = if zstd + jpeg + png > 0.0 {
            libraries / (zstd + jpeg + png)
        } else {
            0.0
        };
        let staged = decode + sweeps + images + projection + superpixels + voxels;
        [
            zstd * scale,
            jpeg * scale,
            png * scale,
            decode - libraries,
            voxels,
            images,
            projection,
            sweeps + superpixels,
            (self.total - staged).max(0.0),
        ]
    }
}

/// The SVG text of the chart of `bars`.
pub fn svg(bars: &[Bar]) -> Result<String, std::fmt::Error> {
    let (left, right, top, row, gap) = (110.0, 60.0, 44.0, 34.0, 18.0);
    let width = 900.0;
    let plot = width - left - right;
    let longest = bars
        .iter()
        .flat_map(|b| [b.total, b.target.unwrap_or(0.0)])
        .fold(1.0, f64::max);
    // Gridlines every 5 or 10 ms, the axis to the next line past the longest bar.
    let step = if longest > 60.0 { 10.0 } else { 5.0 };
    let axis = (longest / step).ceil() * step;
    let x = |ms: f64| left + ms / axis * plot;
    let legend_rows = 3;
    let bars_bottom = top + bars.len() as f64 * (row + gap);
    let height = bars_bottom + 30.0 + legend_rows as f64 * 20.0 + 10.0;
    let mut s = String::new();
    writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" font-size="12">"#
    )?;
    writeln!(s, r#"<rect width="100%" height="100%" fill="white"/>"#)?;
    writeln!(
        s,
        r#"<text x="{left}" y="20" font-size="14">Where one sample's time goes, one core (ms per sample; class-map superpixels, default recipe)</text>"#
    )?;
    let mut tick = 0.0;
    while tick <= axis + 1e-9 {
        let tx = x(tick);
        writeln!(
            s,
            r##"<line x1="{tx:.1}" y1="{top}" x2="{tx:.1}" y2="{bars_bottom}" stroke="#e5e5e5"/><text x="{tx:.1}" y="{:.1}" text-anchor="middle" fill="#555">{tick}</text>"##,
            bars_bottom + 14.0
        )?;
        tick += step;
    }
    for (i, bar) in bars.iter().enumerate() {
        let y = top + i as f64 * (row + gap);
        writeln!(
            s,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"#,
            left - 8.0,
            y + row / 2.0 + 4.0,
            bar.name
        )?;
        let mut at = 0.0;
        for ((name, colour), ms) in SEGMENTS.iter().zip(bar.segments()) {
            if ms <= 0.0 {
                continue;
            }
            let (x0, w) = (x(at), ms / axis * plot);
            writeln!(
                s,
                r#"<rect x="{x0:.1}" y="{y:.1}" width="{w:.1}" height="{row}" fill="{colour}"><title>{name}: {ms:.1} ms</title></rect>"#
            )?;
            if w > 26.0 {
                writeln!(
                    s,
                    r#"<text x="{:.1}" y="{:.1}" text-anchor="middle" font-size="11">{ms:.1}</text>"#,
                    x0 + w / 2.0,
                    y + row / 2.0 + 4.0
                )?;
            }
            at += ms;
        }
        // The total right of the bar, or right of the target line when that is close.
        let end = match bar.target {
            Some(target) if (x(target) - x(bar.total)).abs() < 36.0 => bar.total.max(target),
            _ => bar.total,
        };
        writeln!(
            s,
            r#"<text x="{:.1}" y="{:.1}" font-weight="bold">{:.1}</text>"#,
            x(end) + 5.0,
            y + row / 2.0 + 4.0,
            bar.total
        )?;
        if let Some(target) = bar.target {
            let tx = x(target);
            writeln!(
                s,
                r##"<line x1="{tx:.1}" y1="{:.1}" x2="{tx:.1}" y2="{:.1}" stroke="#222" stroke-width="2" stroke-dasharray="4 3"/><text x="{tx:.1}" y="{:.1}" text-anchor="middle" font-size="11">target {target}</text>"##,
                y - 4.0,
                y + row + 4.0,
                y - 6.0
            )?;
        }
    }
    let per_row = SEGMENTS.len().div_ceil(legend_rows);
    for (k, (name, colour)) in SEGMENTS.iter().enumerate() {
        let lx = left + (k % per_row) as f64 * (plot / per_row as f64);
        let ly = bars_bottom + 30.0 + (k / per_row) as f64 * 20.0;
        writeln!(
            s,
            r#"<rect x="{lx:.1}" y="{:.1}" width="12" height="12" fill="{colour}"/><text x="{:.1}" y="{ly:.1}">{name}</text>"#,
            ly - 10.0,
            lx + 16.0
        )?;
    }
    writeln!(s, "</svg>")?;
    Ok(s)
}
