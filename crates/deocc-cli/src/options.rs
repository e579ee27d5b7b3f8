//! `deocc options`: every pipeline option with its default, range and meaning.

use anyhow::Result;
use clap::Args;

#[derive(Args)]
pub struct OptionsArgs {
    /// As JSON: a list of {name, default, range, meaning}.
    #[arg(long, conflicts_with = "markdown")]
    json: bool,
    /// As the Markdown table of docs/options.md.
    #[arg(long)]
    markdown: bool,
}

pub fn run(a: OptionsArgs) -> Result<()> {
    match print(&a) {
        // `deocc options | head` closes the pipe early: not an error.
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}

fn print(a: &OptionsArgs) -> std::io::Result<()> {
    use deocc_pipeline::options_help::{markdown, table};
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    if a.markdown {
        return write!(out, "{}", markdown());
    }
    let rows = table();
    if a.json {
        let list: Vec<serde_json::Value> = rows
            .iter()
            .map(|(o, d)| {
                serde_json::json!({
                    "name": o.name, "default": d, "range": o.range, "meaning": o.meaning,
                })
            })
            .collect();
        let text = serde_json::to_string_pretty(&list).map_err(std::io::Error::other)?;
        return writeln!(out, "{text}");
    }
    let name_w = rows.iter().map(|(o, _)| o.name.len()).max().unwrap_or(0);
    let def_w = rows
        .iter()
        .map(|(_, d)| d.to_string().len())
        .max()
        .unwrap_or(0);
    let range_w = rows
        .iter()
        .map(|(o, _)| o.range.describe().len())
        .max()
        .unwrap_or(0);
    writeln!(
        out,
        "{:name_w$}  {:def_w$}  {:range_w$}  meaning",
        "option", "default", "range"
    )?;
    for (o, d) in rows {
        writeln!(
            out,
            "{:name_w$}  {:def_w$}  {:range_w$}  {}",
            o.name,
            d.to_string(),
            o.range.describe(),
            o.meaning
        )?;
    }
    writeln!(
        out,
        "\nSet them in a JSON file for `deocc run --options FILE` (nested ones as \
         {{\"depth_clean\": {{\"radius\": 2}}}})."
    )
}
