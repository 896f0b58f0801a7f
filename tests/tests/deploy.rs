//! The container and Kubernetes files (`deploy/docker`, `deploy/compose.yaml`,
//! `deploy/k8s`) checked with what this machine can run: no Docker daemon, no
//! cluster. The manifests are rendered by `kubectl kustomize` (where kubectl is
//! installed; otherwise the base's files are checked unrendered) and validated
//! against the Kubernetes API's schemas, strictly (`kubernetes-validate` from
//! `.deps/bagtools`, offline); the rendered objects must agree with each other and
//! with the image (ports, probes, volumes, config and secret names). The
//! Dockerfile must install with the script `make deps` runs, and its packaging step
//! (`deploy/docker/runtime-packages.sh`) is run on the real server binary.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

use serde::Deserialize;
use serde_yaml::Value;
use stillmap_e2e::{bin, repo_dir, tempfile_path, venv_python};

fn deploy() -> PathBuf {
    repo_dir().join("deploy")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn docs(text: &str) -> Vec<Value> {
    serde_yaml::Deserializer::from_str(text).map(|d| Value::deserialize(d).expect("YAML document")).filter(|v| !v.is_null()).collect()
}

fn str_at<'a>(v: &'a Value, path: &[&str]) -> &'a str {
    let mut cur = v;
    for key in path {
        cur = &cur[*key];
    }
    cur.as_str().unwrap_or_else(|| panic!("{path:?} is not a string in {v:?}"))
}

/// The overlay rendered by `kubectl kustomize`, or `None` without kubectl.
fn render(overlay: &str) -> Option<String> {
    let out = Command::new("kubectl").args(["kustomize"]).arg(deploy().join("k8s").join(overlay)).output().ok()?;
    assert!(out.status.success(), "kubectl kustomize {overlay}: {}", String::from_utf8_lossy(&out.stderr));
    Some(String::from_utf8(out.stdout).expect("utf-8 manifests"))
}

/// The base's resources without kubectl: its files, and the ConfigMaps its
/// `configMapGenerator` makes (without kustomize's name hashes).
fn unrendered_base() -> String {
    let dir = deploy().join("k8s/base");
    let kustomization: Value = serde_yaml::from_str(&read(&dir.join("kustomization.yaml"))).expect("kustomization");
    let mut out = String::new();
    for resource in kustomization["resources"].as_sequence().expect("resources") {
        out += &read(&dir.join(resource.as_str().expect("resource path")));
        out += "\n---\n";
    }
    for generator in kustomization["configMapGenerator"].as_sequence().expect("configMapGenerator") {
        let mut data = serde_yaml::Mapping::new();
        for file in generator["files"].as_sequence().expect("files") {
            let file = file.as_str().expect("file");
            let (key, path) = file.split_once('=').unwrap_or((file, file));
            data.insert(key.into(), read(&dir.join(path)).into());
        }
        let map = serde_yaml::to_string(&serde_yaml::Mapping::from_iter([
            ("apiVersion".into(), "v1".into()),
            ("kind".into(), "ConfigMap".into()),
            ("metadata".into(), Value::Mapping(serde_yaml::Mapping::from_iter([("name".into(), generator["name"].clone())]))),
            ("data".into(), Value::Mapping(data)),
        ]))
        .expect("ConfigMap YAML");
        out += &map;
        out += "\n---\n";
    }
    out
}

/// The schema check of `text` against the API's schemas, rejecting unknown fields.
fn schema_check(text: &str) -> std::process::Output {
    let path = tempfile_path("manifests.yaml");
    std::fs::write(&path, text).expect("write manifests");
    let out = Command::new(venv_python("bagtools"))
        .args(["-m", "kubernetes_validate", "--strict", "--quiet", "-k", "1.32.0"])
        .arg(&path)
        .output()
        .expect("run kubernetes-validate");
    let _ = std::fs::remove_file(&path);
    out
}

/// Validates manifests against the API's schemas, rejecting unknown fields.
fn validate(text: &str) {
    let out = schema_check(text);
    assert!(out.status.success(), "schema check failed:\n{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
}

fn objects(text: &str) -> BTreeMap<(String, String), Value> {
    docs(text).into_iter().map(|d| ((str_at(&d, &["kind"]).to_string(), str_at(&d, &["metadata", "name"]).to_string()), d)).collect()
}

/// The object of `kind` whose name is `name` or `name-<kustomize hash>`.
fn find<'a>(objects: &'a BTreeMap<(String, String), Value>, kind: &str, name: &str) -> &'a Value {
    objects
        .iter()
        .find(|((k, n), _)| k == kind && (n == name || n.strip_prefix(name).is_some_and(|rest| rest.starts_with('-'))))
        .map(|(_, v)| v)
        .unwrap_or_else(|| panic!("no {kind} {name} among {:?}", objects.keys().collect::<Vec<_>>()))
}

fn env_of(container: &Value) -> BTreeMap<String, String> {
    container["env"]
        .as_sequence()
        .map(|env| {
            env.iter()
                .map(|e| {
                    let value = match (e["value"].as_str(), &e["valueFrom"]["secretKeyRef"]) {
                        (Some(v), _) => v.to_string(),
                        (None, secret) if secret.is_mapping() => {
                            format!("secret:{}/{}", str_at(secret, &["name"]), str_at(secret, &["key"]))
                        }
                        (None, _) => format!("fieldRef:{}", str_at(e, &["valueFrom", "fieldRef", "fieldPath"])),
                    };
                    (str_at(e, &["name"]).to_string(), value)
                })
                .collect()
        })
        .unwrap_or_default()
}

fn port_of(address: &str) -> u64 {
    address.rsplit(':').next().and_then(|p| p.parse().ok()).unwrap_or_else(|| panic!("no port in {address}"))
}

/// The server's pod agrees with itself and with the rest: named ports equal the
/// listen addresses, probes ask `/healthz` on the HTTP port, every mount has its
/// volume, the config and the router config come from the generated ConfigMaps,
/// the tokens from the Secret, Zenoh connects to the router's Service.
fn check_server(objects: &BTreeMap<(String, String), Value>) -> Value {
    let set = find(objects, "StatefulSet", "stillmap-server");
    let pod = &set["spec"]["template"]["spec"];
    let container = &pod["containers"][0];
    let env = env_of(container);
    let ports: BTreeMap<String, u64> = container["ports"]
        .as_sequence()
        .expect("container ports")
        .iter()
        .map(|p| (str_at(p, &["name"]).to_string(), p["containerPort"].as_u64().expect("containerPort")))
        .collect();
    assert_eq!(ports["grpc"], port_of(&env["STILLMAP_GRPC_LISTEN"]));
    assert_eq!(ports["http"], port_of(&env["STILLMAP_HTTP_LISTEN"]));
    assert_eq!(ports["zenoh"], port_of(&env["STILLMAP_ZENOH_LISTEN"]));
    for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
        assert_eq!(str_at(container, &[probe, "httpGet", "path"]), "/healthz", "{probe}");
        assert_eq!(str_at(container, &[probe, "httpGet", "port"]), "http", "{probe}");
    }
    let volumes: BTreeMap<String, &Value> =
        pod["volumes"].as_sequence().expect("volumes").iter().map(|v| (str_at(v, &["name"]).to_string(), v)).collect();
    let claims: BTreeSet<String> = set["spec"]["volumeClaimTemplates"]
        .as_sequence()
        .expect("volumeClaimTemplates")
        .iter()
        .map(|c| str_at(c, &["metadata", "name"]).to_string())
        .collect();
    let mounts: BTreeMap<String, String> = container["volumeMounts"]
        .as_sequence()
        .expect("volumeMounts")
        .iter()
        .map(|m| (str_at(m, &["name"]).to_string(), str_at(m, &["mountPath"]).to_string()))
        .collect();
    for name in mounts.keys() {
        assert!(volumes.contains_key(name) || claims.contains(name), "mount {name} has no volume");
    }
    // The files the environment names are where the volumes put them.
    assert_eq!(mounts["config"], env["STILLMAP_CONFIG"]);
    assert!(env["STILLMAP_TOKEN_FILE"].starts_with(&(mounts["tokens"].clone() + "/")));
    assert!(env["STILLMAP_MODEL"].starts_with(&(mounts["models"].clone() + "/")));
    assert!(env["STILLMAP_STORE"].starts_with(&(mounts["store"].clone() + "/")));
    let config_map = str_at(volumes["config"], &["configMap", "name"]);
    assert_eq!(config_map, str_at(find(objects, "ConfigMap", "stillmap-config"), &["metadata", "name"]));
    assert!(find(objects, "ConfigMap", "stillmap-config")["data"]["stillmap-server.toml"].is_string());
    assert_eq!(str_at(volumes["tokens"], &["secret", "secretName"]), "stillmap-tokens");
    // Zenoh: the router's Service and port.
    let router_service = find(objects, "Service", "zenoh-router");
    let router_port = router_service["spec"]["ports"][0]["port"].as_u64().expect("router port");
    assert_eq!(env["STILLMAP_SERVER_ID"], "fieldRef:metadata.name", "the pod's stable name");
    // Robots that ask where to stream are sent to the pod by its name on the
    // StatefulSet's headless Service; Kubernetes expands only variables defined
    // before the one that names them.
    let headless = str_at(&set["spec"], &["serviceName"]);
    assert_eq!(str_at(find(objects, "Service", headless), &["spec", "clusterIP"]), "None");
    assert_eq!(env["STILLMAP_GRPC_ADVERTISE"], format!("http://$(STILLMAP_SERVER_ID).{headless}:{}", ports["grpc"]));
    let names: Vec<&str> = container["env"].as_sequence().expect("env").iter().map(|e| str_at(e, &["name"])).collect();
    let position = |n: &str| names.iter().position(|x| *x == n).expect("env var");
    assert!(position("STILLMAP_SERVER_ID") < position("STILLMAP_GRPC_ADVERTISE"), "defined before it is named");
    assert_eq!(env["STILLMAP_ZENOH_CONNECT"], format!("tcp/{}:{router_port}", str_at(router_service, &["metadata", "name"])));
    let router = find(objects, "Deployment", "zenoh-router");
    let router_volume = &router["spec"]["template"]["spec"]["volumes"][0];
    assert_eq!(
        str_at(router_volume, &["configMap", "name"]),
        str_at(find(objects, "ConfigMap", "zenoh-router-config"), &["metadata", "name"])
    );
    // The shared PostgreSQL: the URL from its Secret, its Service on its container's port.
    assert_eq!(env["STILLMAP_REPLICA_URL"], "secret:stillmap-postgres/replica-url");
    let pg = find(objects, "StatefulSet", "stillmap-postgres");
    let pg_container = &pg["spec"]["template"]["spec"]["containers"][0];
    let pg_env = env_of(pg_container);
    assert_eq!(pg_env["POSTGRES_PASSWORD"], "secret:stillmap-postgres/password");
    let pg_service = find(objects, "Service", "stillmap-postgres");
    assert_eq!(str_at(&pg_service["spec"]["ports"][0], &["targetPort"]), str_at(&pg_container["ports"][0], &["name"]));
    assert_eq!(pg_service["spec"]["ports"][0]["port"].as_u64(), pg_container["ports"][0]["containerPort"].as_u64());
    // The server's Service reaches every port by name.
    let service = find(objects, "Service", "stillmap-server");
    for p in service["spec"]["ports"].as_sequence().expect("service ports") {
        assert!(ports.contains_key(str_at(p, &["targetPort"])), "service port {p:?}");
    }
    container.clone()
}

#[test]
fn kubernetes_manifests_render_and_validate() {
    let base = match render("base") {
        Some(text) => text,
        None => {
            eprintln!("kubectl not installed: checking deploy/k8s/base's files unrendered (the GPU overlay is not rendered)");
            unrendered_base()
        }
    };
    validate(&base);
    let base_objects = objects(&base);
    let container = check_server(&base_objects);
    assert!(str_at(&container, &["image"]).starts_with("stillmap"));
    if let Some(gpu) = render("gpu") {
        validate(&gpu);
        let gpu_objects = objects(&gpu);
        let container = check_server(&gpu_objects);
        assert_eq!(str_at(&container, &["image"]), "stillmap:cuda");
        assert_eq!(container["resources"]["limits"]["nvidia.com/gpu"].as_u64(), Some(1));
        // The same objects as the base's, with the GPU request and image.
        assert_eq!(gpu_objects.keys().collect::<Vec<_>>(), base_objects.keys().collect::<Vec<_>>());
    }
}

/// A manifest with a misspelt field fails the schema check (the check is real).
#[test]
fn the_schema_check_rejects_an_unknown_field() {
    let broken = read(&deploy().join("k8s/base/router.yaml")).replacen("containerPort: 7447", "containerPrt: 7447", 1);
    let out = schema_check(&broken);
    assert!(!out.status.success(), "accepted: {}", String::from_utf8_lossy(&out.stdout));
}

/// The Dockerfile installs with deploy/install-deps.sh, its stages copy only from
/// stages it has, its defaults match the Kubernetes pod's, and its packaging step
/// lists the Debian packages of the real server's libraries.
#[test]
fn the_dockerfile_uses_the_install_script_and_its_packaging_step_works() {
    let dockerfile = read(&deploy().join("docker/Dockerfile"));
    let mut stages = Vec::new();
    for line in dockerfile.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        if words.first() == Some(&"FROM") {
            let from = words[1];
            assert!(from.starts_with("debian:12") || stages.iter().any(|s| s == from), "FROM {from}: Debian 12 or an earlier stage");
            assert_eq!(words.get(2), Some(&"AS"), "{line}");
            stages.push(words[3].to_string());
        }
        if let Some(from) = line.split_whitespace().find_map(|w| w.strip_prefix("--from=")) {
            assert!(stages.iter().any(|s| s == from), "COPY --from={from} before stage {from}");
        }
    }
    assert_eq!(stages, ["build", "cpu", "cuda"]);
    assert!(
        dockerfile.contains("deploy/install-deps.sh --server-only --gpu") && dockerfile.contains("deploy/install-deps.sh --server-only;")
    );
    assert!(dockerfile.contains("HEALTHCHECK") && dockerfile.contains("/healthz"));
    // The image's defaults are what the pod sets.
    let container = check_server(&objects(&unrendered_base()));
    for (key, value) in env_of(&container) {
        if ["STILLMAP_ZENOH_CONNECT", "STILLMAP_TOKEN_FILE", "STILLMAP_SERVER_ID", "STILLMAP_GRPC_ADVERTISE", "STILLMAP_REPLICA_URL"]
            .contains(&key.as_str())
        {
            continue; // set by the deployment, not the image
        }
        assert!(dockerfile.contains(&format!("{key}={value}")), "the Dockerfile's {key} is not {value}");
    }
    let ignored = read(&repo_dir().join(".dockerignore"));
    for path in ["target", ".deps", "dashboard/node_modules"] {
        assert!(ignored.lines().any(|l| l == path), ".dockerignore lacks {path}");
    }
    // The packaging step on the real binary.
    let out = Command::new(deploy().join("docker/runtime-packages.sh")).arg(bin("stillmap-server")).output().expect("runtime-packages.sh");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let packages = String::from_utf8(out.stdout).expect("utf-8");
    for p in ["libc6", "libopencv-core406", "libopencv-video406", "libstdc++6"] {
        assert!(packages.lines().any(|l| l == p), "{p} missing from {packages}");
    }
    // A file that is no binary is refused with a message.
    let out = Command::new(deploy().join("docker/runtime-packages.sh")).arg(deploy().join("compose.yaml")).output().expect("run");
    assert!(!out.status.success());
}

/// The compose file: a router and two servers that connect to it, each with its own
/// store volume and host ports, the router's configuration the Kubernetes one, and
/// the PostgreSQL both copy their commits to.
#[test]
fn the_compose_file_connects_two_servers_to_the_router() {
    let mut compose: Value = serde_yaml::from_str(&read(&deploy().join("compose.yaml"))).expect("compose YAML");
    compose.apply_merge().expect("merge keys");
    let services = compose["services"].as_mapping().expect("services");
    let names: BTreeSet<&str> = services.keys().filter_map(Value::as_str).collect();
    assert_eq!(names, BTreeSet::from(["postgres", "router", "server-a", "server-b"]));
    let pg = &compose["services"]["postgres"];
    let (user, db) = (pg["environment"]["POSTGRES_USER"].as_str(), pg["environment"]["POSTGRES_DB"].as_str());
    let router_config = compose["services"]["router"]["volumes"][0].as_str().expect("router volume");
    let (host, _) = router_config.split_once(':').expect("host:container");
    assert!(deploy().join(host).exists(), "{host}");
    let mut host_ports = BTreeSet::new();
    let mut stores = BTreeSet::new();
    for name in ["server-a", "server-b"] {
        let s = &compose["services"][name];
        assert_eq!(s["image"].as_str(), Some("stillmap:cpu"), "{name}: the anchor's keys merged in");
        let env = &s["environment"];
        assert_eq!(env["STILLMAP_ZENOH_CONNECT"].as_str(), Some("tcp/router:7447"), "{name}");
        assert_eq!(env["STILLMAP_SERVER_ID"].as_str(), Some(name), "{name}: its own id on Zenoh");
        let replica = env["STILLMAP_REPLICA_URL"].as_str().expect("the shared PostgreSQL");
        let expected = format!("postgresql://{}@postgres:5432/{}", user.expect("user"), db.expect("database"));
        assert_eq!(replica, expected, "{name}: the compose file's PostgreSQL, its user and database");
        assert!(s["depends_on"].as_sequence().is_some_and(|d| d.iter().any(|d| d.as_str() == Some("postgres"))), "{name}");
        for p in s["ports"].as_sequence().expect("ports") {
            let p = p.as_str().expect("port mapping");
            assert!(host_ports.insert(p.split(':').next().expect("host port").to_string()), "host port of {p} used twice");
        }
        // Robots asking where to stream are sent to the host port published for its gRPC port.
        let grpc_port = s["ports"]
            .as_sequence()
            .expect("ports")
            .iter()
            .filter_map(Value::as_str)
            .find_map(|p| p.strip_suffix(":50051"))
            .expect("the gRPC port published");
        let advertised = env["STILLMAP_GRPC_ADVERTISE"].as_str().expect("advertised gRPC address");
        assert_eq!(advertised, format!("http://${{STILLMAP_HOST:-127.0.0.1}}:{grpc_port}"), "{name}");
        let store = s["volumes"][0].as_str().expect("store volume");
        assert!(store.ends_with(":/var/lib/stillmap") && stores.insert(store.to_string()), "{store}");
    }
}
