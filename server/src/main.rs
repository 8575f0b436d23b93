use clap::Parser;
use tracing_subscriber::EnvFilter;

fn main() {
    let config = scnerf_server::config::Config::parse();
    // Logs go to stderr; stdout carries only the `listening on` line that scripts read.
    tracing_subscriber::fmt()
        .with_env_filter(EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info,ort=warn")))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("scnerf-server: cannot start the async runtime: {e}");
            std::process::exit(1);
        }
    };
    if let Err(e) = runtime.block_on(scnerf_server::server::run(config)) {
        eprintln!("scnerf-server: {e}");
        std::process::exit(1);
    }
}
