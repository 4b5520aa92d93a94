//! `isochron serve`: the lab service.

use std::{net::SocketAddr, path::PathBuf, sync::Arc};

use anyhow::Context;
use rt_core::params::Scenario;

use crate::{
    AppState, Records, app, check_bind,
    config::{LabMode, ServeConfig},
};

/// The command line of `isochron serve` (each overrides the config file).
#[derive(Debug, Clone, Default)]
pub struct ServeArgs {
    /// `--config FILE`.
    pub config: Option<PathBuf>,
    /// `--bind ADDR`.
    pub bind: Option<SocketAddr>,
    /// `--token TOKEN` (or `ISOCHRON_TOKEN`).
    pub token: Option<String>,
    /// `--web-dir DIR`.
    pub web_dir: Option<PathBuf>,
    /// `--data-dir DIR`.
    pub data_dir: Option<PathBuf>,
    /// `--params FILE` (repeatable): parameter files laid over the scenario, in order.
    pub params: Vec<PathBuf>,
}

/// Runs the service until SIGINT/SIGTERM.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let cfg = match &args.config {
        Some(path) => ServeConfig::from_file(path)?,
        None => ServeConfig::default(),
    };
    let bind = args.bind.unwrap_or(cfg.server.bind);
    let token = args
        .token
        .or_else(|| cfg.server.token.clone())
        .filter(|t| !t.is_empty());
    check_bind(bind, token.as_deref())?;
    let web_dir = args
        .web_dir
        .or_else(|| cfg.server.web_dir.clone())
        .unwrap_or_else(crate::default_web_dir);
    if !web_dir.join("index.html").is_file() {
        tracing::warn!(dir = %web_dir.display(), "dashboard not built (run `make web`); serving the API only");
    }
    let data_dir = args.data_dir.unwrap_or_else(|| cfg.server.data_dir.clone());
    let mut scenario = match &cfg.lab.scenario {
        Some(path) => Scenario::from_file(path)?,
        None => Scenario::default(),
    };
    for path in &args.params {
        scenario = rt_core::tuning::overlay_params_file(&scenario, path)?;
    }
    if cfg.lab.mode == LabMode::Real {
        anyhow::bail!(
            "lab.mode = \"real\": the hardware drivers (FRI client, webcam, magnet) are not wired \
             into `isochron serve` yet; use mode = \"simulated\""
        );
    }
    let records = Arc::new(Records::open(&data_dir)?);
    tracing::info!(data_dir = %data_dir.display(), scenario = %scenario.name, "trial records ready");
    let options = crate::LabOptions {
        state_hz: cfg.server.state_hz,
        ws_send_timeout: std::time::Duration::from_millis(cfg.server.ws_send_timeout_ms),
        ..crate::LabOptions::default()
    };
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(1, |d| d.as_secs());
    let (lab, sim) =
        crate::simlab::start_simulated(scenario, Some(Arc::clone(&records)), options, seed)?;
    tracing::info!(
        fri = ?sim.runtime().fri_local_addr(),
        "simulated lab running (simulated pendulum, rendered camera through the detector, \
         robot over loopback UDP FRI, magnet on its fake board)"
    );

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("isochron-http")
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let state = Arc::new(
        AppState::new(web_dir)
            .with_token(token)
            .with_records(records)
            .with_lab(Arc::clone(&lab))
            .with_body_limit(cfg.server.body_limit_bytes)
            .with_cors_origins(cfg.server.cors_origins.clone()),
    );
    let result = runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(bind)
            .await
            .with_context(|| format!("cannot listen on {bind}"))?;
        let local = listener.local_addr()?;
        println!("isochron {} listening on http://{local}/", crate::VERSION);
        axum::serve(crate::tuned_listener(listener), app(state))
            .with_graceful_shutdown(shutdown_signal())
            .await
            .context("server failed")
    });
    lab.shutdown();
    drop(sim);
    result?;
    tracing::info!("shut down cleanly");
    Ok(())
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
