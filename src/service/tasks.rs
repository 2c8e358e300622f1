//! The service's background tasks, watched: one that ends while the service runs (it panicked,
//! or its loop returned) is a problem `/healthz` reports, never a silent stop.

use futures::FutureExt as _;
use std::future::Future;
use std::panic::AssertUnwindSafe;
use std::sync::{Arc, Mutex};
use tokio::sync::watch;
use tokio::task::JoinHandle;

/// The tasks that stopped while the service ran, each with why.
#[derive(Debug, Default, Clone)]
pub struct TaskWatch {
    ended: Arc<Mutex<Vec<String>>>,
}

impl TaskWatch {
    /// Spawns `task` under watch. When it ends before `stopping` turns true (a panic, or a
    /// loop that returned), the end is logged as an error and kept as a problem.
    pub fn spawn<F>(
        &self,
        name: &'static str,
        stopping: watch::Receiver<bool>,
        task: F,
    ) -> JoinHandle<()>
    where
        F: Future<Output = ()> + Send + 'static,
    {
        let ended = Arc::clone(&self.ended);
        tokio::spawn(async move {
            let outcome = AssertUnwindSafe(task).catch_unwind().await;
            if *stopping.borrow() {
                return;
            }
            let why = match outcome {
                Ok(()) => "its loop ended".to_owned(),
                Err(panic) => format!("it panicked: {}", panic_message(panic.as_ref())),
            };
            tracing::error!(task = name, why = %why,
                "a background task stopped while the service runs; restart the service");
            ended
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .push(format!(
                    "the {name} task stopped while the service runs ({why}); restart the service"
                ));
        })
    }

    /// The tasks that stopped, and why; `None` while all run.
    pub fn problem(&self) -> Option<String> {
        let ended = self.ended.lock().unwrap_or_else(|p| p.into_inner());
        (!ended.is_empty()).then(|| ended.join("; "))
    }
}

/// The text of a panic's payload.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_task_that_panics_or_returns_while_running_is_a_problem() {
        let watch = TaskWatch::default();
        let (stop_tx, stop_rx) = watch::channel(false);
        assert_eq!(watch.problem(), None);
        watch
            .spawn("uploader", stop_rx.clone(), async {
                panic!("a duration overflowed");
            })
            .await
            .unwrap();
        let problem = watch.problem().expect("the panic is a problem");
        assert!(
            problem.contains("the uploader task stopped")
                && problem.contains("a duration overflowed"),
            "{problem}"
        );
        watch
            .spawn("retention", stop_rx.clone(), async {})
            .await
            .unwrap();
        let problem = watch.problem().unwrap();
        assert!(
            problem.contains("uploader") && problem.contains("the retention task stopped"),
            "{problem}"
        );
        // Ending with the service is no problem.
        let quiet = TaskWatch::default();
        stop_tx.send_replace(true);
        quiet.spawn("liveness", stop_rx, async {}).await.unwrap();
        assert_eq!(quiet.problem(), None);
    }
}
