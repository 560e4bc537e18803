//! `stylenerf bench coordinator`: job creation, lease cycle and GetJob latency benchmark of an
//! embedded coordinator on loopback (the body lives in `stylenerf_server::bench`).

use stylenerf_server::bench::{run as run_bench, BenchOptions};

pub fn run(options: BenchOptions) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    println!(
        "coordinator benchmark: loopback gRPC, SQLite WAL file, {} submitters, {} workers, {} clients",
        options.submitters, options.workers, options.clients
    );
    let report = runtime.block_on(run_bench(&options))?;
    println!("{report}");
    Ok(())
}
