//! A one-node Slurm cluster on this machine for the tests: Debian's
//! `munged`, `slurmctld` and `slurmd` (packages `munge` and `slurm-wlm`,
//! which `scripts/test.sh` installs) in the foreground, each in its own
//! process group, with every file (key, sockets, state, logs, `slurm.conf`)
//! in a temporary folder and the controller on free loopback ports. Client
//! commands find it through `SLURM_CONF` ([`SlurmCluster::env`]). Dropping
//! the cluster cancels its jobs and kills the daemons. It runs as root
//! (`SlurmUser=root`), as CI does.

use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// How long the cluster may take to come up.
const START_DEADLINE: Duration = Duration::from_secs(60);

/// The running cluster.
pub struct SlurmCluster {
    pub dir: tempfile::TempDir,
    pub partition: &'static str,
    children: Vec<(&'static str, Child)>,
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

fn short_hostname() -> String {
    let name = fs::read_to_string("/proc/sys/kernel/hostname").expect("hostname");
    name.trim()
        .split('.')
        .next()
        .unwrap_or("localhost")
        .to_string()
}

impl SlurmCluster {
    /// Starts munged, slurmctld and slurmd and waits until the node is idle.
    pub fn start() -> SlurmCluster {
        let dir = tempfile::tempdir().expect("tempdir");
        let d = dir.path();
        for sub in ["munge", "state", "spool", "log"] {
            fs::create_dir_all(d.join(sub)).expect("mkdir");
        }
        fs::set_permissions(d.join("munge"), fs::Permissions::from_mode(0o700)).expect("chmod");
        let mut key = vec![0u8; 1024];
        {
            use std::io::Read;
            fs::File::open("/dev/urandom")
                .and_then(|mut f| f.read_exact(&mut key))
                .expect("/dev/urandom");
        }
        fs::write(d.join("munge/munge.key"), key).expect("munge key");
        fs::set_permissions(d.join("munge/munge.key"), fs::Permissions::from_mode(0o400))
            .expect("chmod key");
        let host = short_hostname();
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        let conf = format!(
            "ClusterName=rigdtest
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort={ctld}
SlurmdPort={slurmd}
AuthType=auth/munge
AuthInfo=socket={d}/munge/munge.sock
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation={d}/state
SlurmdSpoolDir={d}/spool
SlurmctldPidFile={d}/slurmctld.pid
SlurmdPidFile={d}/slurmd.pid
SlurmctldLogFile={d}/log/slurmctld.log
SlurmdLogFile={d}/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
MpiDefault=none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerParameters=batch_sched_delay=0
NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN
PartitionName=rigd Nodes={host} Default=YES MaxTime=INFINITE State=UP
",
            ctld = free_port(),
            slurmd = free_port(),
            d = d.display(),
        );
        fs::write(d.join("slurm.conf"), conf).expect("slurm.conf");
        let mut cluster = SlurmCluster {
            dir,
            partition: "rigd",
            children: Vec::new(),
        };
        let d = cluster.dir.path().to_path_buf();
        let munge_args = [
            "-F".to_string(),
            "--force".into(),
            format!("--socket={}/munge/munge.sock", d.display()),
            format!("--key-file={}/munge/munge.key", d.display()),
            format!("--log-file={}/log/munged.log", d.display()),
            format!("--pid-file={}/munge/munged.pid", d.display()),
            format!("--seed-file={}/munge/seed", d.display()),
        ];
        cluster.spawn("munged", "munged", &munge_args);
        cluster.wait_for("munged's socket", || d.join("munge/munge.sock").exists());
        let conf = d.join("slurm.conf").display().to_string();
        cluster.spawn(
            "slurmctld",
            "slurmctld",
            &["-D".into(), "-f".into(), conf.clone()],
        );
        cluster.spawn(
            "slurmd",
            "slurmd",
            &["-D".into(), "-f".into(), conf, "-N".into(), host],
        );
        let env = cluster.env();
        cluster.wait_for("the node to be idle", || {
            Command::new("sinfo")
                .args(["-h", "-o", "%T"])
                .envs(env.iter().map(|(k, v)| (k, v)))
                .output()
                .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "idle")
        });
        cluster
    }

    /// The environment Slurm's client commands need to reach this cluster.
    pub fn env(&self) -> Vec<(String, String)> {
        vec![(
            "SLURM_CONF".into(),
            self.dir.path().join("slurm.conf").display().to_string(),
        )]
    }

    /// A Slurm client command against this cluster; its stdout.
    pub fn command(&self, program: &str, args: &[&str]) -> String {
        let out = Command::new(program)
            .args(args)
            .envs(self.env())
            .output()
            .unwrap_or_else(|e| panic!("{program}: {e}"));
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// The controller's log, for a failing assertion's message.
    pub fn logs(&self) -> String {
        ["slurmctld", "slurmd"]
            .iter()
            .map(|n| {
                let path = self.dir.path().join(format!("log/{n}.log"));
                let text = fs::read_to_string(&path).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(20).collect();
                format!(
                    "--- {n}.log (last lines)\n{}",
                    tail.into_iter().rev().collect::<Vec<_>>().join("\n")
                )
            })
            .collect::<Vec<_>>()
            .join("\n")
    }

    fn spawn(&mut self, name: &'static str, program: &str, args: &[String]) {
        let log = fs::File::create(self.dir.path().join(format!("log/{name}.out"))).expect("log");
        let err = log.try_clone().expect("log");
        let child = Command::new(program)
            .args(args)
            .envs(self.env())
            .stdin(Stdio::null())
            .stdout(log)
            .stderr(err)
            .process_group(0)
            .spawn()
            .unwrap_or_else(|e| {
                panic!("cannot start {program} (scripts/test.sh installs munge and slurm-wlm): {e}")
            });
        self.children.push((name, child));
    }

    fn wait_for(&mut self, what: &str, ready: impl Fn() -> bool) {
        let started = Instant::now();
        while !ready() {
            let exited = self
                .children
                .iter_mut()
                .find_map(|(name, child)| Some((*name, child.try_wait().ok()??)));
            if let Some((name, status)) = exited {
                panic!(
                    "{name} exited ({status}) while waiting for {what}\n{}",
                    self.logs_of(name)
                );
            }
            assert!(
                started.elapsed() < START_DEADLINE,
                "waited {START_DEADLINE:?} for {what}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn logs_of(&self, name: &str) -> String {
        let out = self.dir.path().join(format!("log/{name}.out"));
        let log = self.dir.path().join(format!("log/{name}.log"));
        format!(
            "{}\n{}",
            fs::read_to_string(out).unwrap_or_default(),
            fs::read_to_string(log).unwrap_or_default()
        )
    }

    /// The folder of the cluster's files.
    pub fn path(&self) -> &Path {
        self.dir.path()
    }
}

impl Drop for SlurmCluster {
    fn drop(&mut self) {
        let _ = Command::new("scancel")
            .args(["--me", "--full"])
            .envs(self.env())
            .output();
        for (_, child) in self.children.iter_mut().rev() {
            // SAFETY: kill(2) of the child's own process group.
            unsafe {
                libc::kill(-(child.id() as i32), libc::SIGKILL);
            }
            let _ = child.wait();
        }
    }
}
