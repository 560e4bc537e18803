use clap::Parser;
#[derive(Parser)]
struct A {
    #[command(flatten)]
    o: stylenerf_server::bench::BenchOptions,
}
#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let a = A::parse();
    println!("{}", stylenerf_server::bench::run(&a.o).await?);
    Ok(())
}
