//! `flowram merge`: the outputs of the shards of one collection (dataset folders) or one
//! evaluation (`bench success --out` files) combined into one dataset or one success table.
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use flowram::rollout::collection::merge_collections;
use flowram::rollout::evaluation::merge_success_records;

#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Every shard's output: the dataset folders of `collect`, or the results files of
    /// `bench success --out` (all of one kind).
    #[arg(required = true)]
    shards: Vec<PathBuf>,
    /// Where the merged dataset folder (new or empty) or results file goes. Required for
    /// datasets; for results files optional (the table is printed either way).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

pub fn run(args: MergeArgs) -> anyhow::Result<()> {
    let folders = args.shards.iter().filter(|p| p.is_dir()).count();
    if folders == args.shards.len() {
        let out = args.out.context("merging datasets needs --out DIR: the new dataset folder")?;
        let report = merge_collections(&args.shards, &out)?;
        if args.json {
            return super::print_json(&report);
        }
        println!(
            "{}: {} episodes from {} shards into {}{}",
            report.task,
            report.episodes,
            report.shards,
            out.display(),
            if report.given_up > 0 {
                format!(" ({} slots failed every attempt)", report.given_up)
            } else {
                String::new()
            }
        );
        if report.revisions.len() > 1 {
            println!("note: the shards come from different source revisions: {}", report.revisions.join(", "));
        }
        return Ok(());
    }
    anyhow::ensure!(
        folders == 0,
        "give either dataset folders (from `collect`) or results files (from `bench success --out`), not both"
    );
    let merged = merge_success_records(&args.shards)?;
    if let Some(out) = &args.out {
        merged.write(out)?;
    }
    let table = merged.table();
    if args.json {
        return super::print_json(&table);
    }
    println!("{} ({} shards merged):", merged.checkpoint, args.shards.len());
    super::bench_policy::print_success_table(&table);
    Ok(())
}
