//! `inspect`: what the drives hold, as text or as the JSON report.

use crate::cli::Args;
use superflow_pipeline::inspect::InspectReport;

pub fn run(args: &Args, json: bool) -> anyhow::Result<()> {
    let labels = args.config()?.labels;
    let dataset = crate::open::dataset(args)?;
    let report = InspectReport::with_labels(&dataset, &labels).with_fleet(&dataset);
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.to_text());
    }
    Ok(())
}
