// Package validate checks fleetmem's Kubernetes manifests (k8s/) against the
// real Kubernetes API types: every kustomization is rendered with kustomize's
// own library, every object is decoded strictly (an unknown or misspelt
// field, a wrong type or a duplicate field fails) into the k8s.io/api type of
// its kind, and the objects are checked against each other (selectors,
// named ports, config maps, claims, probes, resources).
//
//	cd k8s/validate && go test ./...      (make test-k8s)
package validate

import (
	"fmt"
	"path/filepath"
	"strings"
	"testing"

	appsv1 "k8s.io/api/apps/v1"
	corev1 "k8s.io/api/core/v1"
	networkingv1 "k8s.io/api/networking/v1"
	policyv1 "k8s.io/api/policy/v1"
	"k8s.io/apimachinery/pkg/labels"
	"k8s.io/apimachinery/pkg/runtime"
	"k8s.io/apimachinery/pkg/runtime/serializer"
	"k8s.io/apimachinery/pkg/util/intstr"
	"sigs.k8s.io/kustomize/api/krusty"
	"sigs.k8s.io/kustomize/kyaml/filesys"
)

// The kustomizations a user applies.
var kustomizations = []string{"../base", "../overlays/example", "../overlays/cluster"}

// Secrets and claims the operator creates before applying
// (docs/deployment.md); anything else referenced must be in the manifests.
var external = map[string]bool{
	"Secret/fleetmem-server-tls":                true,
	"Secret/fleetmem-credentials":               true,
	"Secret/fleetmem-robot-1-token":             true,
	"Secret/fleetmem-peer-token":                true,
	"PersistentVolumeClaim/fleetmem-recordings": true,
}

func strictDecoder(t *testing.T) runtime.Decoder {
	t.Helper()
	scheme := runtime.NewScheme()
	for _, add := range []func(*runtime.Scheme) error{
		corev1.AddToScheme, appsv1.AddToScheme, policyv1.AddToScheme,
		networkingv1.AddToScheme,
	} {
		if err := add(scheme); err != nil {
			t.Fatal(err)
		}
	}
	return serializer.NewCodecFactory(scheme, serializer.EnableStrict).
		UniversalDeserializer()
}

// render runs kustomize on dir and returns each object's YAML.
func render(t *testing.T, dir string) []string {
	t.Helper()
	abs, err := filepath.Abs(dir)
	if err != nil {
		t.Fatal(err)
	}
	k := krusty.MakeKustomizer(krusty.MakeDefaultOptions())
	resources, err := k.Run(filesys.MakeFsOnDisk(), abs)
	if err != nil {
		t.Fatalf("kustomize build %s: %v", dir, err)
	}
	var out []string
	for _, r := range resources.Resources() {
		y, err := r.AsYAML()
		if err != nil {
			t.Fatal(err)
		}
		out = append(out, string(y))
	}
	return out
}

func decodeAll(t *testing.T, docs []string) ([]runtime.Object, error) {
	decoder := strictDecoder(t)
	var objects []runtime.Object
	for _, doc := range docs {
		obj, gvk, err := decoder.Decode([]byte(doc), nil, nil)
		if err != nil {
			head := doc
			if i := strings.Index(head, "spec:"); i > 0 {
				head = head[:i]
			}
			return nil, fmt.Errorf("%v\nin:\n%s", err, head)
		}
		if gvk.Kind == "" {
			return nil, fmt.Errorf("object without a kind:\n%s", doc)
		}
		objects = append(objects, obj)
	}
	return objects, nil
}

// podSpecs returns each workload's name and pod template.
type workload struct {
	name     string
	selector map[string]string
	template corev1.PodTemplateSpec
}

func workloads(objects []runtime.Object) []workload {
	var out []workload
	for _, o := range objects {
		switch w := o.(type) {
		case *appsv1.StatefulSet:
			out = append(out, workload{"StatefulSet/" + w.Name, w.Spec.Selector.MatchLabels, w.Spec.Template})
		case *appsv1.Deployment:
			out = append(out, workload{"Deployment/" + w.Name, w.Spec.Selector.MatchLabels, w.Spec.Template})
		}
	}
	return out
}

func containerPort(c corev1.Container, port intstr.IntOrString) bool {
	for _, p := range c.Ports {
		if (port.Type == intstr.String && p.Name == port.StrVal) ||
			(port.Type == intstr.Int && p.ContainerPort == port.IntVal) {
			return true
		}
	}
	return false
}

func checkProbe(errs *[]string, where string, c corev1.Container, p *corev1.Probe) {
	if p == nil {
		return
	}
	switch {
	case p.HTTPGet != nil:
		if !containerPort(c, p.HTTPGet.Port) {
			*errs = append(*errs, fmt.Sprintf("%s: probe port %s is not a port of the container", where, p.HTTPGet.Port.String()))
		}
		if !strings.HasPrefix(p.HTTPGet.Path, "/") {
			*errs = append(*errs, fmt.Sprintf("%s: probe path %q", where, p.HTTPGet.Path))
		}
	case p.GRPC != nil, p.TCPSocket != nil:
	case p.Exec != nil:
		if len(p.Exec.Command) == 0 {
			*errs = append(*errs, fmt.Sprintf("%s: empty exec probe", where))
		}
	default:
		*errs = append(*errs, fmt.Sprintf("%s: probe without a handler", where))
	}
}

// consistencyErrors lists what strict decoding cannot: that the objects
// refer to each other correctly.
func consistencyErrors(objects []runtime.Object) []string {
	var errs []string
	errorf := func(format string, args ...any) { errs = append(errs, fmt.Sprintf(format, args...)) }
	have := map[string]bool{}
	for _, o := range objects {
		m, ok := o.(interface{ GetName() string })
		if !ok {
			continue
		}
		kind := fmt.Sprintf("%T", o)
		kind = kind[strings.LastIndex(kind, ".")+1:]
		have[kind+"/"+m.GetName()] = true
	}
	exists := func(ref string) bool { return have[ref] || external[ref] }
	ws := workloads(objects)
	if len(ws) == 0 {
		return append(errs, "no workloads")
	}
	var serverPods []map[string]string
	for _, w := range ws {
		if !labels.SelectorFromSet(w.selector).Matches(labels.Set(w.template.Labels)) {
			errorf("%s: selector %v does not match its pod labels %v", w.name, w.selector, w.template.Labels)
		}
		spec := w.template.Spec
		if spec.SecurityContext == nil || spec.SecurityContext.RunAsNonRoot == nil || !*spec.SecurityContext.RunAsNonRoot {
			errorf("%s: pods must run as non-root", w.name)
		}
		volumes := map[string]bool{}
		for _, v := range spec.Volumes {
			volumes[v.Name] = true
			switch {
			case v.ConfigMap != nil && !exists("ConfigMap/"+v.ConfigMap.Name):
				errorf("%s: config map %s is not defined", w.name, v.ConfigMap.Name)
			case v.Secret != nil && !exists("Secret/"+v.Secret.SecretName):
				errorf("%s: secret %s is neither defined nor documented", w.name, v.Secret.SecretName)
			case v.PersistentVolumeClaim != nil && !exists("PersistentVolumeClaim/"+v.PersistentVolumeClaim.ClaimName):
				errorf("%s: claim %s is not defined", w.name, v.PersistentVolumeClaim.ClaimName)
			}
		}
		if ss, ok := findStatefulSet(objects, w.name); ok {
			for _, c := range ss.Spec.VolumeClaimTemplates {
				volumes[c.Name] = true
			}
			// The NATS StatefulSet of the cluster overlay is not a server.
			if ss.Name == "fleetmem-server" {
				serverPods = append(serverPods, w.template.Labels)
			}
			if !exists("Service/" + ss.Spec.ServiceName) {
				errorf("%s: serviceName %s is not a Service", w.name, ss.Spec.ServiceName)
			}
		}
		for _, c := range spec.Containers {
			where := w.name + "/" + c.Name
			for _, m := range c.VolumeMounts {
				if !volumes[m.Name] {
					errorf("%s: mounts unknown volume %s", where, m.Name)
				}
			}
			if c.LivenessProbe == nil {
				errorf("%s: no liveness probe", where)
			}
			checkProbe(&errs, where+" liveness", c, c.LivenessProbe)
			checkProbe(&errs, where+" readiness", c, c.ReadinessProbe)
			checkProbe(&errs, where+" startup", c, c.StartupProbe)
			if c.Resources.Requests.Cpu().IsZero() || c.Resources.Requests.Memory().IsZero() ||
				c.Resources.Limits.Cpu().IsZero() || c.Resources.Limits.Memory().IsZero() {
				errorf("%s: cpu and memory requests and limits are required", where)
			}
			if c.Resources.Limits.Memory().Cmp(*c.Resources.Requests.Memory()) < 0 {
				errorf("%s: memory limit below its request", where)
			}
		}
	}
	if len(serverPods) != 1 {
		return append(errs, fmt.Sprintf("want one server StatefulSet, have %d", len(serverPods)))
	}
	server := serverPods[0]
	selects := func(sel map[string]string) bool {
		return len(sel) > 0 && labels.SelectorFromSet(sel).Matches(labels.Set(server))
	}
	var grpc, http, pdb, policy bool
	for _, o := range objects {
		switch x := o.(type) {
		case *corev1.Service:
			matched := false
			for _, w := range ws {
				if labels.SelectorFromSet(x.Spec.Selector).Matches(labels.Set(w.template.Labels)) {
					matched = true
					for _, p := range x.Spec.Ports {
						ok := false
						for _, c := range w.template.Spec.Containers {
							ok = ok || containerPort(c, p.TargetPort)
						}
						if !ok {
							errorf("Service/%s: targetPort %s is not a container port of %s", x.Name, p.TargetPort.String(), w.name)
						}
						grpc = grpc || p.Port == 50051
						http = http || p.Port == 8080
					}
				}
			}
			if !matched {
				errorf("Service/%s: selector %v matches no pods", x.Name, x.Spec.Selector)
			}
		case *policyv1.PodDisruptionBudget:
			pdb = pdb || selects(x.Spec.Selector.MatchLabels)
		case *networkingv1.NetworkPolicy:
			policy = policy || selects(x.Spec.PodSelector.MatchLabels)
		}
	}
	if !grpc || !http {
		errorf("want Services for gRPC (50051) and HTTP (8080): grpc=%v http=%v", grpc, http)
	}
	if !pdb {
		errorf("no PodDisruptionBudget selects the server")
	}
	if !policy {
		errorf("no NetworkPolicy selects the server")
	}
	return errs
}

func findStatefulSet(objects []runtime.Object, name string) (*appsv1.StatefulSet, bool) {
	for _, o := range objects {
		if s, ok := o.(*appsv1.StatefulSet); ok && "StatefulSet/"+s.Name == name {
			return s, true
		}
	}
	return nil, false
}

func TestKustomizationsRenderToValidObjects(t *testing.T) {
	for _, dir := range kustomizations {
		t.Run(filepath.Base(dir), func(t *testing.T) {
			objects, err := decodeAll(t, render(t, dir))
			if err != nil {
				t.Fatal(err)
			}
			for _, e := range consistencyErrors(objects) {
				t.Error(e)
			}
		})
	}
}

// The validation is not vacuous: a misspelt field, a wrong type and a
// broken reference in the real manifests each fail it.
func TestValidationCatchesMistakes(t *testing.T) {
	docs := render(t, "../base")
	mutations := []struct{ name, from, to string }{
		{"misspelt livenessProbe", "livenessProbe:", "livenessProbee:"},
		{"misspelt containerPort", "containerPort: 50051", "containerPorts: 50051"},
		{"string for replicas", "replicas: 1", "replicas: one"},
	}
	for _, m := range mutations {
		t.Run(m.name, func(t *testing.T) {
			changed := false
			var mutated []string
			for _, d := range docs {
				if strings.Contains(d, m.from) && !changed {
					d = strings.Replace(d, m.from, m.to, 1)
					changed = true
				}
				mutated = append(mutated, d)
			}
			if !changed {
				t.Fatalf("%q is not in the manifests", m.from)
			}
			if _, err := decodeAll(t, mutated); err == nil {
				t.Errorf("%s: decoded without an error", m.name)
			} else {
				t.Logf("rejected as expected: %v", strings.SplitN(err.Error(), "\n", 2)[0])
			}
		})
	}
	t.Run("probe on a port the container lacks", func(t *testing.T) {
		objects, err := decodeAll(t, docs)
		if err != nil {
			t.Fatal(err)
		}
		for _, o := range objects {
			if s, ok := o.(*appsv1.StatefulSet); ok {
				s.Spec.Template.Spec.Containers[0].ReadinessProbe.HTTPGet.Port = intstr.FromString("metrics")
			}
		}
		if errs := consistencyErrors(objects); len(errs) == 0 {
			t.Error("a probe on an unknown port passed the checks")
		} else {
			t.Logf("rejected as expected: %s", errs[0])
		}
	})
	t.Run("Service selecting no pods", func(t *testing.T) {
		objects, err := decodeAll(t, docs)
		if err != nil {
			t.Fatal(err)
		}
		for _, o := range objects {
			if s, ok := o.(*corev1.Service); ok && s.Name == "fleetmem-grpc" {
				s.Spec.Selector = map[string]string{"app.kubernetes.io/name": "fleetmem-sever"}
			}
		}
		if errs := consistencyErrors(objects); len(errs) == 0 {
			t.Error("a Service selecting nothing passed the checks")
		} else {
			t.Logf("rejected as expected: %s", errs[0])
		}
	})
}
