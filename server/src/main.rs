//! `isochron`: the lab service and its command-line tools (CONTRACT.md, "Commands").

use std::{net::SocketAddr, path::PathBuf, process::ExitCode, sync::Arc};

use anyhow::Context;
use clap::{Parser, Subcommand};
use rt_core::params::Scenario;
use server::{AppState, app, check_bind};
use tracing_subscriber::EnvFilter;

#[derive(Debug, Parser)]
#[command(name = "isochron", version = server::VERSION, about = "Timed interception of a swinging ball by a KUKA LBR iiwa 7")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the lab service (the simulated lab unless a config says otherwise).
    Serve {
        /// Address to listen on; anything but loopback needs --token.
        #[arg(long, default_value = "127.0.0.1:8080")]
        bind: SocketAddr,
        /// Bearer token required for every command endpoint.
        #[arg(long, env = "ISOCHRON_TOKEN")]
        token: Option<String>,
        /// Folder of the built dashboard (default: web/dist of this source tree).
        #[arg(long)]
        web_dir: Option<PathBuf>,
    },
    /// Scenario files.
    Scenario {
        #[command(subcommand)]
        command: ScenarioCommand,
    },
}

#[derive(Debug, Subcommand)]
enum ScenarioCommand {
    /// Validate a scenario file and print it fully resolved (defaults filled in) as JSON.
    Check {
        /// The scenario file (TOML).
        file: PathBuf,
    },
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line naming what was wrong (CONTRACT.md).
            let chain: Vec<String> = e.chain().map(ToString::to_string).collect();
            eprintln!("isochron: {}", chain.join(": "));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Serve {
            bind,
            token,
            web_dir,
        } => serve(bind, token, web_dir.unwrap_or_else(server::default_web_dir)),
        Command::Scenario {
            command: ScenarioCommand::Check { file },
        } => {
            let scenario = Scenario::from_file(&file)?;
            print_out(&serde_json::to_string_pretty(&scenario)?)
        }
    }
}

fn serve(bind: SocketAddr, token: Option<String>, web_dir: PathBuf) -> anyhow::Result<()> {
    check_bind(bind, token.as_deref())?;
    if !web_dir.join("index.html").is_file() {
        tracing::warn!(dir = %web_dir.display(), "dashboard not built (run `make web`); serving the API only");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("isochron-http")
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(bind)
            .await
            .with_context(|| format!("cannot listen on {bind}"))?;
        let local = listener.local_addr()?;
        println!("isochron {} listening on http://{local}/", server::VERSION);
        let state = Arc::new(AppState::new(web_dir));
        axum::serve(listener, app(state))
            .with_graceful_shutdown(shutdown_signal())
            .await
            .context("server failed")?;
        tracing::info!("shut down cleanly");
        Ok(())
    })
}

async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
}

/// Writes a line to stdout; a closed pipe (`| head`) is not an error.
fn print_out(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match writeln!(out, "{text}").and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}
