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
    if let Ok(load) = std::fs::read_to_string("/proc/loadavg") {
        let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
        println!(
            "machine: {cores} cores, load average {} (1/5/15 min) before the run",
            load.split_whitespace()
                .take(3)
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    let report = runtime.block_on(run_bench(&options))?;
    println!("{report}");
    Ok(())
}
