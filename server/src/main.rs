use clap::Parser;
use scnerf_server::config::Config;
use scnerf_server::logging;

fn main() {
    scnerf_server::sysmem::return_large_blocks();
    let config = Config::parse();
    // Logs go to stderr; stdout carries only the `listening on` line that scripts read.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let subscriber = logging::subscriber(config.log_format, logging::env_filter(), std::io::stderr, ansi);
    // try_init also routes the `log` crate's records into tracing.
    if let Err(e) = tracing_subscriber::util::SubscriberInitExt::try_init(subscriber) {
        eprintln!("scnerf-server: cannot install the logger: {e}");
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("scnerf-server: cannot start the async runtime: {e}");
            std::process::exit(1);
        }
    };
    let result = runtime.block_on(scnerf_server::server::run(config));
    // Past the grace period, requests still running are abandoned: do not wait for their
    // blocking tasks (image decoding or encoding) either.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    if let Err(e) = result {
        eprintln!("scnerf-server: {e}");
        std::process::exit(1);
    }
}
