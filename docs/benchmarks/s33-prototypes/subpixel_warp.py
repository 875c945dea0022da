"""DISK keypoint localisation under known homographies: six fox frames warped (rotation, scale, slight
perspective), mutual nearest detections within 2 px, per sub-pixel method (thirty-third session).
Run from the repository root with FAVORMAP's DISK installed; reads ../shared/data/fox/images."""
import numpy as np, torch, torch.nn.functional as F, cv2, os, sys
from favormap.features.base import create
from favormap.features.heatmap import subpixel_offsets
ex = create("disk", max_keypoints=2048)
D=os.path.join(os.path.dirname(__file__),'../../../../shared/data/fox/images/'); names=sorted(os.listdir(D))
def heat_of(img):
    h,w=img.shape[:2]
    x=torch.from_numpy(np.ascontiguousarray(img)).permute(2,0,1)[None].float()/255
    ph,pw=(-h)%16,(-w)%16
    x=F.pad(x,(0,pw,0,ph))
    with torch.inference_mode():
        hid=ex._trunk(x); conv=ex._head; r=conv.kernel_size[0]//2
        heat=F.conv2d(hid,conv.weight[128:],conv.bias[128:],padding=r)[0,0,:h,:w]
    return heat
def methods(heat):
    xy,sc=ex._detect(heat)
    H,W=heat.shape
    out={"int":xy.float().numpy()}
    out["parab"]=(xy.float()+subpixel_offsets(heat,xy)).numpy()
    # 2D quadratic (Hessian) on 3x3
    x=xy[:,0].clamp(1,W-2); y=xy[:,1].clamp(1,H-2)
    g=lambda dy,dx: heat[y+dy,x+dx].double()
    dx=(g(0,1)-g(0,-1))/2; dy=(g(1,0)-g(-1,0))/2
    dxx=g(0,1)-2*g(0,0)+g(0,-1); dyy=g(1,0)-2*g(0,0)+g(-1,0); dxy=(g(1,1)-g(1,-1)-g(-1,1)+g(-1,-1))/4
    det=dxx*dyy-dxy**2
    ox=-(dyy*dx-dxy*dy)/det; oy=-(dxx*dy-dxy*dx)/det
    good=(det>0)&(dxx<0)
    ox=torch.where(good,ox,0*ox).clamp(-0.5,0.5); oy=torch.where(good,oy,0*oy).clamp(-0.5,0.5)
    out["quad2d"]=(xy.double()+torch.stack([ox,oy],1)).float().numpy()
    for T in (0.3,1.0,3.0,10.0):
      for k in (3,5):
        r=k//2
        hp=F.pad(heat[None,None],(r,r,r,r),mode='replicate')[0,0]
        offs=torch.arange(-r,r+1)
        yy=xy[:,1][:,None,None]+r+offs[None,:,None]; xx=xy[:,0][:,None,None]+r+offs[None,None,:]
        patch=hp[yy,xx]
        wgt=torch.softmax((patch.reshape(len(xy),-1)-patch.reshape(len(xy),-1).max(1,keepdim=True)[0])/T,1).reshape(patch.shape)
        sx=(wgt*offs[None,None,:]).sum((1,2)); sy=(wgt*offs[None,:,None]).sum((1,2))
        out[f"soft{k}T{T}"]=(xy.float()+torch.stack([sx,sy],1)).numpy()
    return out
rng=np.random.default_rng(0)
res={}
for it in range(6):
    img=cv2.imread(D+names[it*6])[:,:,::-1]; img=cv2.resize(img,(360,640),interpolation=cv2.INTER_AREA)
    h,w=img.shape[:2]
    a=np.radians(rng.uniform(-8,8)); s=rng.uniform(0.9,1.1)
    c=np.array([w/2,h/2])
    A=np.array([[s*np.cos(a),-s*np.sin(a)],[s*np.sin(a),s*np.cos(a)]])
    t=c-A@c+rng.uniform(-3,3,2)
    Hm=np.eye(3); Hm[:2,:2]=A; Hm[:2,2]=t
    Hm[2,:2]=rng.uniform(-1e-4,1e-4,2)
    img2=cv2.warpPerspective(img,Hm,(w,h),flags=cv2.INTER_LINEAR,borderMode=cv2.BORDER_REFLECT)
    hh=heat_of(img); print('heat at peaks', hh.max().item(), hh.std().item()) if it==0 else None
    m1=methods(heat_of(img)); m2=methods(heat_of(img2))
    for k in m1:
        # pixel-centre convention: heat index i <-> coordinate i (warpPerspective maps pixel centres at integer coords)
        p=np.c_[m1[k],np.ones(len(m1[k]))]@Hm.T; p=p[:,:2]/p[:,2:]
        q=m2[k]
        d=np.linalg.norm(p[:,None]-q[None],axis=2)
        j=d.argmin(1); i2=d.argmin(0)
        mut=i2[j]==np.arange(len(p))
        dd=d[np.arange(len(p)),j][mut]
        dd=dd[dd<2]
        res.setdefault(k,[]).append(dd)
for k,v in res.items():
    v=np.concatenate(v); print(f"{k:10s} n={len(v)} med={np.median(v):.3f} mean={v.mean():.3f} <0.5:{(v<0.5).mean():.2f}")
