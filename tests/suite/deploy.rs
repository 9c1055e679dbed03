//! `deploy/`: the Grafana dashboard queries only metrics the server exports,
//! the provisioning files name each other correctly, compose publishes the
//! metrics port the docs curl, and the systemd unit's documentation exists.

use std::path::Path;
use tofwave::telemetry::ALL_METRICS;

fn deploy(path: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy").join(path)).unwrap()
}

/// Every `tofwave_*` metric the dashboard's queries name, histogram suffixes removed.
pub fn dashboard_metrics() -> Vec<String> {
    let json: serde_json::Value = serde_json::from_str(&deploy("grafana/dashboards/tofwave.json")).unwrap();
    let mut exprs = Vec::new();
    for p in json["panels"].as_array().unwrap() {
        for t in p["targets"].as_array().unwrap() {
            exprs.push(t["expr"].as_str().unwrap().to_string());
        }
    }
    for v in json["templating"]["list"].as_array().unwrap() {
        exprs.push(v["definition"].as_str().unwrap().to_string());
    }
    let mut names = Vec::new();
    for e in exprs {
        let mut rest = e.as_str();
        while let Some(i) = rest.find("tofwave_") {
            let tail = &rest[i..];
            let end = tail.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(tail.len());
            let mut name = &tail[..end];
            for suffix in ["_bucket", "_sum", "_count"] {
                name = name.strip_suffix(suffix).unwrap_or(name);
            }
            names.push(name.to_string());
            rest = &tail[end..];
        }
    }
    names.sort();
    names.dedup();
    names
}

#[test]
fn the_grafana_dashboard_queries_only_exported_metrics() {
    let names = dashboard_metrics();
    assert!(names.len() >= 10, "{names:?}");
    for n in &names {
        assert!(ALL_METRICS.contains(&n.as_str()), "the dashboard queries {n}, which src/telemetry.rs does not define");
    }
    // Every panel reads the provisioned data source by its uid.
    let json: serde_json::Value = serde_json::from_str(&deploy("grafana/dashboards/tofwave.json")).unwrap();
    let ds = deploy("grafana/datasource.yml");
    for p in json["panels"].as_array().unwrap() {
        let uid = p["datasource"]["uid"].as_str().unwrap();
        assert!(ds.contains(&format!("uid: {uid}")), "panel {} reads data source {uid}", p["title"]);
    }
    // The panels the dashboard promises.
    let titles: Vec<&str> = json["panels"].as_array().unwrap().iter().map(|p| p["title"].as_str().unwrap()).collect();
    for want in ["Frames per second", "Rejected", "False-alarm rate vs design", "latency percentiles", "Lag"] {
        assert!(titles.iter().any(|t| t.contains(want)), "no panel {want:?}: {titles:?}");
    }
}

#[test]
fn compose_publishes_metrics_and_provisions_grafana() {
    let compose = deploy("docker-compose.yml");
    assert!(compose.contains("\"9090:9090\""), "compose does not publish the metrics port");
    assert!(deploy("Dockerfile").contains("--metrics\", \"0.0.0.0:9090\""));
    assert!(deploy("prometheus.yml").contains("tofwave:9090"));
    for mount in ["./grafana/dashboards.yml:/etc/grafana/provisioning/dashboards/", "./grafana/dashboards:/var/lib/grafana/dashboards"] {
        assert!(compose.contains(mount), "compose lacks {mount}");
    }
    assert!(deploy("grafana/dashboards.yml").contains("path: /var/lib/grafana/dashboards"));
    assert!(deploy("Dockerfile").contains("COPY assets ./assets"), "the image build needs the embedded font");
}

#[test]
fn the_systemd_units_documentation_is_installed_by_its_own_steps() {
    let unit = deploy("tofwave.service");
    let docs: Vec<&str> = unit
        .lines()
        .filter_map(|l| l.strip_prefix("Documentation="))
        .flat_map(|l| l.split_whitespace())
        .collect();
    assert!(!docs.is_empty());
    for d in docs {
        let path = d.strip_prefix("file://").expect("file:// documentation");
        // An install step copies a repository file to that path.
        let step = unit
            .lines()
            .find(|l| l.starts_with('#') && l.contains("install") && l.trim_end().ends_with(path))
            .unwrap_or_else(|| panic!("no install step for {path}"));
        let src = step.split_whitespace().rev().nth(1).unwrap();
        assert!(Path::new(env!("CARGO_MANIFEST_DIR")).join(src).is_file(), "{src} (installed as {path}) is not in the repository");
    }
}

/// `ALL_METRICS` lists every metric name `src/telemetry.rs` defines (the
/// list the dashboard test trusts; two names were once missing from it).
#[test]
fn all_metrics_lists_every_metric_name_defined() {
    let src = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/telemetry.rs")).unwrap();
    let mut defined = Vec::new();
    for line in src.lines().filter(|l| l.trim_start().starts_with("pub const ")) {
        if let Some(i) = line.find("\"tofwave_") {
            let name = &line[i + 1..];
            defined.push(name[..name.find('"').unwrap()].to_string());
        }
    }
    assert!(defined.len() >= 16, "{defined:?}");
    for n in &defined {
        assert!(ALL_METRICS.contains(&n.as_str()), "{n} is defined in src/telemetry.rs but missing from ALL_METRICS");
    }
    assert_eq!(defined.len(), ALL_METRICS.len(), "{defined:?}");
}

/// The scale-out compose file: three NATS servers routed to each other with
/// JetStream, three tofwave nodes with distinct ids, each given every NATS
/// server and three replicas, each reachable on its own gRPC port.
#[test]
fn cluster_compose_joins_three_nodes_to_three_nats_servers() {
    let compose = deploy("docker-compose.cluster.yml");
    let conf = deploy("config/nats.conf");
    assert!(conf.contains("jetstream") && conf.contains("store_dir: /data"), "{conf}");
    for n in 1..=3 {
        assert!(conf.contains(&format!("nats://nats-{n}:6222")), "nats.conf routes lack nats-{n}");
        assert!(compose.contains(&format!("\"--name\", \"nats-{n}\"")), "no NATS server nats-{n}");
        assert!(compose.contains(&format!("\"--node-id\", \"tofwave-{n}\"")), "no tofwave node tofwave-{n}");
        assert!(compose.contains(&format!("\"5005{n}:50051\"")), "tofwave-{n} publishes no gRPC port");
    }
    let all = "\"--cluster\", \"nats://nats-1:4222,nats://nats-2:4222,nats://nats-3:4222\"";
    assert_eq!(compose.matches(all).count(), 3, "every node is given every NATS server");
    assert_eq!(compose.matches("\"--cluster-replicas\", \"3\"").count(), 3);
}
